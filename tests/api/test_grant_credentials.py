"""Every change to a grant records the credential that made it, an API token cannot widen a
grant it did not wholly make, and revoking a token undoes the grants it made or changed
(issue 37.2, docs/grants.md)."""

from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.grant_terms import grant_terms_make
from sharing.models import Grant, GrantChange
from sharing.services.grants import grant_create, grant_terms_change
from tests.api.conftest import GRANTS, session_client, token_client

pytestmark = pytest.mark.django_db


@pytest.fixture
def alice(make_robot):
    return make_robot("alice")


@pytest.fixture
def bob(make_owner):
    return make_owner("bob")


def _in(**delta) -> str:
    return (timezone.now() + timedelta(**delta)).replace(microsecond=0).isoformat()


def _browser_grant(alice, bob, on_commit):
    """Alice's grant to Bob made in the browser: one robot, a week."""
    terms = grant_terms_make(
        owner=alice.owner,
        robots=[alice.robot.pk],
        expires_at=timezone.now() + timedelta(days=7),
    )
    with on_commit(execute=True):
        return grant_create(owner=alice.owner, grantee=bob, terms=terms)


def test_a_token_cannot_widen_a_grant_made_in_the_browser(
    alice, bob, make_owner_token, django_capture_on_commit_callbacks
):
    grant = _browser_grant(alice, bob, django_capture_on_commit_callbacks)
    before = (list(grant.scope_robots), grant.expires_at)
    _token, key = make_owner_token(alice.owner, scopes=("share",))
    thief = token_client(key)
    for wider in (
        {},  # all records, never expires: the audit's attack
        {"robots": [str(alice.robot.pk)]},  # same robot, no expiry
        {"robots": [str(alice.robot.pk)], "expires_at": _in(days=30)},  # a later expiry
    ):
        answer = thief.patch(f"{GRANTS}bob/", wider, format="json")
        assert answer.status_code == 403, answer.content
        assert answer.json()["error"] == "token_cannot_widen"
    grant.refresh_from_db()
    assert (list(grant.scope_robots), grant.expires_at) == before
    assert grant.changes.count() == 1  # only its creation
    # Narrowing is allowed, and recorded with the token.
    narrower = {"robots": [str(alice.robot.pk)], "topics": ["/odom"], "expires_at": _in(days=1)}
    with django_capture_on_commit_callbacks(execute=True):
        answer = thief.patch(f"{GRANTS}bob/", narrower, format="json")
    assert answer.status_code == 200, answer.content
    change = grant.changes.first()
    assert (change.kind, change.made_with, change.token_id) == ("changed", "token", _token.pk)


def test_every_change_records_its_credential(
    alice, bob, make_owner_token, django_capture_on_commit_callbacks
):
    token, key = make_owner_token(alice.owner, scopes=("share",))
    api = token_client(key)
    with django_capture_on_commit_callbacks(execute=True):
        assert api.post(GRANTS, {"grantee": "bob"}, format="json").status_code == 201
        # Its own grant, untouched by anyone else: the token may widen it again after narrowing.
        assert api.patch(f"{GRANTS}bob/", {"topics": ["/a"]}, format="json").status_code == 200
        assert api.patch(f"{GRANTS}bob/", {}, format="json").status_code == 200
        owner_browser = session_client(alice.owner)
        assert (
            owner_browser.patch(f"{GRANTS}bob/", {"topics": ["/b"]}, format="json").status_code
            == 200
        )
        # Changed in the browser since: the token may no longer widen it.
        assert api.patch(f"{GRANTS}bob/", {}, format="json").status_code == 403
        assert api.delete(f"{GRANTS}bob/").status_code == 200
    grant = Grant.objects.get(owner=alice.owner, grantee=bob)
    history = list(grant.changes.order_by("id").values_list("kind", "made_with", "token"))
    assert history == [
        ("created", "token", token.pk),
        ("changed", "token", token.pk),
        ("changed", "token", token.pk),
        ("changed", "session", None),
        ("revoked", "token", token.pk),
    ]
    assert grant.changes.get(kind="revoked").terms_before["topics"] == ["/b"]


def test_revoking_a_token_restores_the_grants_it_changed_and_revokes_those_it_made(
    alice, make_owner, make_owner_token, django_capture_on_commit_callbacks
):
    bob, carol = make_owner("bob"), make_owner("carol")
    grant = _browser_grant(alice, bob, django_capture_on_commit_callbacks)
    before = (list(grant.scope_robots), list(grant.scope_topics), grant.expires_at)
    token, key = make_owner_token(alice.owner, scopes=("share",))
    thief = token_client(key)
    hour = _in(hours=1)
    with django_capture_on_commit_callbacks(execute=True):
        # The thief narrows Bob's grant to nothing useful, twice, and grants Carol everything.
        for topics in (["/nothing", "/at-all"], ["/nothing"]):
            changed = thief.patch(
                f"{GRANTS}bob/",
                {"robots": [str(alice.robot.pk)], "topics": topics, "expires_at": hour},
                format="json",
            )
            assert changed.status_code == 200, changed.content
        assert thief.post(GRANTS, {"grantee": "carol"}, format="json").status_code == 201

    browser = session_client(alice.owner)
    url = reverse("api-token-revoke", args=[token.pk])
    page = browser.get(url).content.decode()
    assert 'data-testid="api-token-changed-grant" data-grantee="bob"' in page
    assert 'data-testid="api-token-grant" data-grantee="carol"' in page
    assert 'name="restore_grants" value="yes" checked' in page
    with django_capture_on_commit_callbacks(execute=True):
        answer = browser.post(url, {"revoke_grants": "yes", "restore_grants": "yes"})
    assert answer.status_code == 302
    grant.refresh_from_db()
    assert (list(grant.scope_robots), list(grant.scope_topics), grant.expires_at) == before
    assert grant.status == Grant.Status.ACTIVE  # confirmed again on chain
    restored = grant.changes.first()
    assert (restored.kind, restored.made_with) == (GrantChange.Kind.CHANGED, "session")
    assert Grant.objects.get(owner=alice.owner, grantee=carol).status == Grant.Status.REVOKED


def test_a_restored_grant_whose_former_expiry_passed_is_revoked(
    alice, bob, make_owner_token, django_capture_on_commit_callbacks
):
    grant = _browser_grant(alice, bob, django_capture_on_commit_callbacks)
    token, _key = make_owner_token(alice.owner, scopes=("share",))
    narrower = grant_terms_make(
        owner=alice.owner, robots=[alice.robot.pk], expires_at=timezone.now() + timedelta(hours=1)
    )
    with django_capture_on_commit_callbacks(execute=True):
        grant_terms_change(
            owner=alice.owner, grantee=bob, terms=narrower, made_with="token", made_with_token=token
        )
    # As if a week had passed: the terms before the token's change have expired.
    GrantChange.objects.filter(grant=grant, kind="changed").update(
        terms_before={**grant.changes.get(kind="changed").terms_before, "expires_at": _in(days=-1)}
    )
    with django_capture_on_commit_callbacks(execute=True):
        session_client(alice.owner).post(
            reverse("api-token-revoke", args=[token.pk]), {"restore_grants": "yes"}
        )
    grant.refresh_from_db()
    assert grant.status == Grant.Status.REVOKED
