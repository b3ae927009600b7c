"""`/api/v1/grants/`: granting and revoking access, by username or address, and refusals."""

import pytest
from django.utils.crypto import get_random_string

from accounts.models import ChainState
from accounts.services.owners import owner_create
from sharing.models import Grant
from smcrypto import sm4
from tests.api.conftest import GRANTS, session_client
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


@pytest.fixture
def alice(make_robot):
    return make_robot("alice")


@pytest.fixture
def bob(make_robot):
    return make_robot("bob")


@pytest.fixture
def grant(django_capture_on_commit_callbacks):
    """POST a grant; the chain transaction (queued on commit) runs inline."""

    def post(client, grantee, **kwargs):
        with django_capture_on_commit_callbacks(execute=True):
            return client.post(GRANTS, {"grantee": grantee}, format="json", **kwargs)

    return post


@pytest.fixture
def revoke(django_capture_on_commit_callbacks):
    def delete(client, grantee):
        with django_capture_on_commit_callbacks(execute=True):
            return client.delete(f"{GRANTS}{grantee}/")

    return delete


def _grants() -> list[tuple[str, str, str]]:
    return sorted(
        Grant.objects.values_list("owner__user__username", "grantee__user__username", "status")
    )


def test_grant_list_and_revoke_by_username(alice, bob, grant, revoke, owner_api):
    alice_api, bob_api = owner_api(alice.owner), owner_api(bob.owner)
    answer = grant(alice_api, "bob")
    assert answer.status_code == 201, answer.content
    created = answer.json()
    assert (created["owner"], created["grantee"], created["status"]) == ("alice", "bob", "pending")
    assert created["grantee_address"] == bob.owner.eoa_address
    assert _grants() == [("alice", "bob", "active")]

    given = alice_api.get(GRANTS).json()
    assert [(g["grantee"], g["status"]) for g in given["given"]] == [("bob", "active")]
    assert given["given"][0]["grant_tx"].startswith("0x")
    assert given["received"] == []
    received = bob_api.get(GRANTS).json()
    assert [(g["owner"], g["status"]) for g in received["received"]] == [("alice", "active")]
    assert received["given"] == []

    answer = revoke(alice_api, "bob")
    assert answer.status_code == 200
    assert answer.json()["status"] == "revoking"
    assert _grants() == [("alice", "bob", "revoked")]
    assert alice_api.get(GRANTS).json()["given"][0]["revoke_tx"].startswith("0x")


def test_grant_and_revoke_by_address_in_any_case(alice, bob, grant, revoke, owner_api):
    alice_api = owner_api(alice.owner)
    assert grant(alice_api, bob.owner.eoa_address.lower()).status_code == 201
    assert revoke(alice_api, bob.owner.eoa_address.upper().replace("0X", "0x")).status_code == 200
    assert _grants() == [("alice", "bob", "revoked")]
    # Granted again after a revocation: a new grant.
    assert grant(alice_api, bob.owner.eoa_address).status_code == 201
    assert _grants() == [("alice", "bob", "active"), ("alice", "bob", "revoked")]


def test_a_browser_session_grants_with_its_csrf_token(alice, bob, grant):
    browser = session_client(alice.owner, enforce_csrf=True)
    refused = grant(browser, "bob")
    assert refused.status_code == 403
    assert "CSRF" in refused.json()["detail"]
    assert _grants() == []
    token = get_random_string(32)  # what the login page would have set as the cookie
    browser.cookies["csrftoken"] = token
    answer = grant(browser, "bob", HTTP_X_CSRFTOKEN=token)
    assert answer.status_code == 201
    assert _grants() == [("alice", "bob", "active")]


def test_grant_refusals_change_nothing(alice, bob, grant, owner_api):
    alice_api = owner_api(alice.owner)
    assert grant(alice_api, "bob").status_code == 201
    with_no_chain = owner_create(
        username="carol", password=TEST_PASSWORD, sm4_key=sm4.generate_key()
    )
    assert with_no_chain.chain_state == ChainState.PENDING  # never registered: nothing ran
    before = _grants()
    cases = [
        ("alice", 400, "self_grant"),
        (alice.owner.eoa_address, 400, "self_grant"),
        ("bob", 409, "already_granted"),
        (bob.owner.eoa_address.lower(), 409, "already_granted"),
        ("nobody", 404, "owner_not_found"),
        ("0x" + "00" * 20, 404, "owner_not_found"),
        ("0xnot-an-address", 404, "owner_not_found"),
        ("carol", 409, "grantee_not_registered"),
    ]
    for grantee, status, error in cases:
        answer = grant(alice_api, grantee)
        assert (answer.status_code, answer.json()["error"]) == (status, error), grantee
    assert _grants() == before


def test_an_owner_not_registered_yet_cannot_grant(bob, grant, make_robot, owner_api):
    newcomer = make_robot("dave")
    type(newcomer.owner).objects.filter(pk=newcomer.owner.pk).update(chain_state=ChainState.PENDING)
    answer = grant(owner_api(newcomer.owner), "bob")
    assert answer.status_code == 409
    assert answer.json()["error"] == "not_registered_yet"
    assert _grants() == []


def test_malformed_grant_requests_get_400(alice, grant, owner_api):
    alice_api = owner_api(alice.owner)
    bodies = [b"{}", b"[]", b'{"grantee": 5}', b'{"grantee": ""}', b'{"grantee": null}']
    bodies += [b'{"grantee": "' + b"x" * 151 + b'"}', b'{"grantee": "a\\u0000b"}', b"{"]
    for body in bodies:
        answer = alice_api.generic("POST", GRANTS, body, content_type="application/json")
        assert answer.status_code == 400, body
        assert answer.json()["error"] in ("invalid_request", "malformed_request"), body
    assert _grants() == []


def test_revoke_refusals(alice, bob, grant, revoke, owner_api):
    alice_api = owner_api(alice.owner)
    for grantee, error in [
        ("bob", "no_grant"),
        ("nobody", "owner_not_found"),
        ("%00", "owner_not_found"),
        ("x" * 300, "owner_not_found"),
        ("alice", "no_grant"),
    ]:
        answer = revoke(alice_api, grantee)
        assert answer.status_code == 404, grantee
        assert answer.json()["error"] == error, grantee
    assert grant(alice_api, "bob").status_code == 201
    assert revoke(alice_api, "bob").status_code == 200
    again = revoke(alice_api, "bob")
    assert (again.status_code, again.json()["error"]) == (404, "no_grant")
    # Bob cannot revoke what Alice gave him.
    bob_side = revoke(owner_api(bob.owner), "alice")
    assert (bob_side.status_code, bob_side.json()["error"]) == (404, "no_grant")


def test_grants_need_credentials(client, alice):
    assert client.get(GRANTS).status_code == 401
    assert client.post(GRANTS, {"grantee": "alice"}).status_code == 401
    assert client.delete(f"{GRANTS}alice/").status_code == 401
    assert _grants() == []
