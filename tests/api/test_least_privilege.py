"""Least privilege through a real server (F1): a stolen robot token uploads and reads the status
of that robot's own uploads, nothing else; owner API tokens are scoped, expire, are revoked,
are stored hashed, and the grants they made are taken back with them."""

import base64
import hashlib
from datetime import timedelta

import pytest
import requests
from django.db import connection
from django.test import Client
from django.utils import timezone
from django.utils.crypto import get_random_string

from accounts.models import AccountEvent, OwnerToken
from accounts.services.api_tokens import owner_token_revoke
from accounts.services.robots import robot_create
from sharing.models import Grant, Record, Verdict
from sharing.services.grants import grant_create
from sharing.services.uploads import record_create_batch
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db(transaction=True)


class Api:
    """`requests` against the live server with one credential."""

    def __init__(self, base: str, token: str | None = None, cookies: dict | None = None) -> None:
        self.base = base
        self.session = requests.Session()
        if token is not None:
            self.session.headers["Authorization"] = f"Token {token}"
        for name, value in (cookies or {}).items():
            self.session.cookies.set(name, value)

    def get(self, path: str, **kwargs: object) -> requests.Response:
        return self.session.get(f"{self.base}{path}", timeout=30, **kwargs)

    def post(self, path: str, **kwargs: object) -> requests.Response:
        return self.session.post(f"{self.base}{path}", timeout=30, **kwargs)

    def delete(self, path: str) -> requests.Response:
        return self.session.delete(f"{self.base}{path}", timeout=30)


def _refused(answer: requests.Response, status: int, error: str) -> dict:
    assert answer.status_code == status, answer.text
    body = answer.json()
    assert body["error"] == error, body
    return body


@pytest.fixture
def world(live_server, make_robot, django_capture_on_commit_callbacks):
    """Alice with two robots and records of each; Bob, who shares his records with Alice;
    Carol, to whom Alice gave access in the portal. All anchored."""
    alice, bob, carol = make_robot("alice"), make_robot("bob"), make_robot("carol")
    sibling, _ = robot_create(owner=alice.owner, name="sibling")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=bob.owner, grantee=alice.owner)
        grant_create(owner=alice.owner, grantee=carol.owner)
        own = record_create_batch(robot=alice.robot, envelopes=[alice.seal(1)])[0]
        siblings = record_create_batch(
            robot=sibling, envelopes=[seal_for(sibling, alice.key, seq=1)]
        )[0]
        shared = record_create_batch(robot=bob.robot, envelopes=[bob.seal(1)])[0]
    return {
        "url": live_server.url,
        "alice": alice,
        "bob": bob,
        "carol": carol,
        "own": str(own.id),
        "sibling": str(siblings.id),
        "shared": str(shared.id),
    }


def _grants() -> list[tuple[str, str, str]]:
    return sorted(
        Grant.objects.values_list("owner__user__username", "grantee__user__username", "status")
    )


# --- robot tokens ----------------------------------------------------------------------------


def test_a_robot_token_uploads_and_reads_the_status_of_its_own_uploads_only(world):
    alice = world["alice"]
    robot = Api(world["url"], alice.token)
    data = base64.b64encode(alice.seal(2)).decode()
    uploaded = robot.post("/api/v1/records/", json={"envelope": data})
    assert uploaded.status_code == 201, uploaded.text
    new = uploaded.json()["id"]

    listed = robot.get("/api/v1/records/")
    assert listed.status_code == 200
    assert {record["id"] for record in listed.json()["results"]} == {world["own"], new}
    for record_id in (world["own"], new):
        detail = robot.get(f"/api/v1/records/{record_id}/")
        assert detail.status_code == 200
        assert detail.json()["status"] in ("pending", "anchored")
    # Not the records of its owner's other robot, nor what others shared with its owner.
    for record_id in (world["sibling"], world["shared"]):
        _refused(robot.get(f"/api/v1/records/{record_id}/"), 404, "not_found")
    filtered = robot.get("/api/v1/records/", params={"owner": "bob"})
    assert filtered.json()["results"] == []


def test_a_robot_token_cannot_read_content_not_even_its_own(world):
    robot = Api(world["url"], world["alice"].token)
    for record_id in (world["own"], world["sibling"], world["shared"]):
        body = _refused(
            robot.get(f"/api/v1/records/{record_id}/content/"), 403, "permission_denied"
        )
        assert "robot token" in body["detail"]
        assert "owner API token" in body["detail"]
        assert "`read`" in body["detail"]
    assert not Verdict.objects.exists()  # nothing was even opened


def test_a_robot_token_cannot_list_grant_or_revoke(world):
    robot = Api(world["url"], world["alice"].token)
    before = _grants()
    body = _refused(robot.get("/api/v1/grants/"), 403, "permission_denied")
    assert "`share`" in body["detail"]
    _refused(robot.post("/api/v1/grants/", json={"grantee": "bob"}), 403, "permission_denied")
    _refused(robot.delete("/api/v1/grants/carol/"), 403, "permission_denied")
    assert _grants() == before


# --- owner API tokens ------------------------------------------------------------------------


def test_owner_token_scopes_are_enforced(world, make_owner_token):
    alice = world["alice"].owner
    _, read_key = make_owner_token(alice, scopes=("read",))
    _, share_key = make_owner_token(alice, scopes=("share",))
    reader, sharer = Api(world["url"], read_key), Api(world["url"], share_key)

    listed = reader.get("/api/v1/records/")
    assert listed.status_code == 200
    # The owner's own records (both robots) and what Bob shares.
    expected = {world["own"], world["sibling"], world["shared"]}
    assert {record["id"] for record in listed.json()["results"]} == expected
    assert reader.get(f"/api/v1/records/{world['shared']}/").status_code == 200
    content = reader.get(f"/api/v1/records/{world['shared']}/content/")
    assert content.status_code == 200, content.text
    assert content.json()["verified"] is True
    for answer in (
        reader.get("/api/v1/grants/"),
        reader.post("/api/v1/grants/", json={"grantee": "bob"}),
        reader.delete("/api/v1/grants/carol/"),
    ):
        body = _refused(answer, 403, "insufficient_scope")
        assert "`share`" in body["detail"]

    assert sharer.get("/api/v1/grants/").status_code == 200
    for path in ("", f"{world['own']}/", f"{world['own']}/content/"):
        body = _refused(sharer.get(f"/api/v1/records/{path}"), 403, "insufficient_scope")
        assert "`read`" in body["detail"]
    # No owner token uploads: that is the robot's.
    data = base64.b64encode(world["alice"].seal(5)).decode()
    _refused(reader.post("/api/v1/records/", json={"envelope": data}), 403, "permission_denied")
    assert Record.objects.count() == 3


def test_expired_and_revoked_owner_tokens_answer_401(world, make_owner_token):
    alice = world["alice"].owner
    expired, expired_key = make_owner_token(alice)
    OwnerToken.objects.filter(pk=expired.pk).update(
        expires_at=timezone.now() - timedelta(seconds=1)
    )
    revoked, revoked_key = make_owner_token(alice)
    assert Api(world["url"], revoked_key).get("/api/v1/records/").status_code == 200
    owner_token_revoke(token=revoked, actor=alice.user)
    for key, word in ((expired_key, "expired"), (revoked_key, "revoked")):
        api = Api(world["url"], key)
        for answer in (api.get("/api/v1/records/"), api.get("/api/v1/grants/")):
            body = _refused(answer, 401, "not_authenticated")
            assert word in body["detail"]
    unknown = Api(world["url"], "aro_" + "x" * 43).get("/api/v1/records/")
    _refused(unknown, 401, "not_authenticated")


def test_an_owner_token_is_stored_hashed_and_its_use_noted(world, make_owner_token):
    alice = world["alice"].owner
    token, key = make_owner_token(alice, scopes=("read",))
    assert key.startswith("aro_")
    assert len(key) > 40
    assert token.token_hash == hashlib.sha256(key.encode()).hexdigest()
    assert token.token_prefix == key[:12]
    assert token.last_used_at is None
    with connection.cursor() as cursor:
        for table in (OwnerToken._meta.db_table, AccountEvent._meta.db_table):
            cursor.execute(f"SELECT * FROM {table}")  # noqa: S608 (fixed table names)
            assert key not in repr(cursor.fetchall()), table
    assert AccountEvent.objects.get(kind=AccountEvent.Kind.TOKEN_CREATED).actor == alice.user

    assert Api(world["url"], key).get("/api/v1/records/").status_code == 200
    token.refresh_from_db()
    first_use = token.last_used_at
    assert first_use is not None
    # Used again within the minute: not written again.
    assert Api(world["url"], key).get("/api/v1/records/").status_code == 200
    token.refresh_from_db()
    assert token.last_used_at == first_use


# --- grants made with a token, taken back with it ---------------------------------------------


def _browser(owner) -> tuple[dict[str, str], str]:
    """An owner's signed-in browser: its cookies and the CSRF token to post with."""
    client = Client()
    client.force_login(owner.user)
    csrf = get_random_string(32)
    return {"sessionid": client.cookies["sessionid"].value, "csrftoken": csrf}, csrf


def test_a_grant_records_the_token_and_revoking_the_token_can_take_it_back(
    world, make_owner, make_owner_token
):
    alice = world["alice"].owner
    dave = make_owner("dave")
    make_owner("erin")
    stolen, stolen_key = make_owner_token(alice, scopes=("share",))
    thief = Api(world["url"], stolen_key)
    for grantee in ("dave", "erin"):
        answer = thief.post("/api/v1/grants/", json={"grantee": grantee})
        assert answer.status_code == 201, answer.text
        assert answer.json()["made_with"] == "token"
    made = Grant.objects.filter(made_with_token=stolen)
    assert sorted(made.values_list("grantee__user__username", "status")) == [
        ("dave", "active"),
        ("erin", "active"),
    ]
    assert set(made.values_list("made_with", flat=True)) == {"token"}
    assert Grant.objects.get(grantee=world["carol"].owner).made_with == "session"

    cookies, csrf = _browser(alice)
    browser = Api(world["url"], cookies=cookies)
    page = browser.get(f"/account/tokens/{stolen.pk}/revoke/")
    assert page.status_code == 200
    assert 'data-grantee="dave"' in page.text
    assert 'data-grantee="erin"' in page.text
    assert 'data-grantee="carol"' not in page.text  # given in the portal, not with the token
    assert "Also revoke these 2 grants" in page.text
    answer = browser.post(
        f"/account/tokens/{stolen.pk}/revoke/",
        data={"csrfmiddlewaretoken": csrf, "revoke_grants": "yes"},
        allow_redirects=False,
    )
    assert answer.status_code == 302, answer.text

    _refused(thief.get("/api/v1/grants/"), 401, "not_authenticated")
    assert sorted(made.values_list("grantee__user__username", "status")) == [
        ("dave", "revoked"),
        ("erin", "revoked"),
    ]
    assert Grant.objects.get(grantee=world["carol"].owner).status == Grant.Status.ACTIVE
    dave_reads = Api(world["url"], make_owner_token(dave)[1])
    assert dave_reads.get("/api/v1/records/", params={"owner": "alice"}).json()["results"] == []
    _refused(dave_reads.get(f"/api/v1/records/{world['own']}/content/"), 404, "not_found")


def test_revoking_a_token_without_the_box_leaves_its_grants(world, make_owner_token):
    alice = world["alice"].owner
    token, key = make_owner_token(alice, scopes=("share",))
    assert (
        Api(world["url"], key).post("/api/v1/grants/", json={"grantee": "bob"}).status_code == 201
    )
    cookies, csrf = _browser(alice)
    answer = Api(world["url"], cookies=cookies).post(
        f"/account/tokens/{token.pk}/revoke/",
        data={"csrfmiddlewaretoken": csrf},
        allow_redirects=False,
    )
    assert answer.status_code == 302
    token.refresh_from_db()
    assert token.revoked_at is not None
    assert Grant.objects.get(made_with_token=token).status == Grant.Status.ACTIVE
