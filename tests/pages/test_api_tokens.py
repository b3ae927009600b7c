"""Owner API tokens' pages: made with the password re-typed and shown once, listed with their
state and last use, revoked with the grants they made, and only by their owner."""

import re
from datetime import timedelta

import pytest
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from accounts.models import AccountEvent, OwnerToken
from accounts.selectors import owner_token_by_key
from accounts.services.api_tokens import owner_token_revoke
from sharing.models import Grant
from sharing.services.grants import grant_create
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

TOKENS = reverse("api-tokens")


def _make(client: Client, **fields: object):
    form = {
        "name": "nightly-export",
        "scopes": ["read"],
        "expires_in_days": "30",
        "password": TEST_PASSWORD,
        **fields,
    }
    return client.post(TOKENS, form)


def test_a_token_is_shown_once_and_only_its_hash_kept(login, pending_owner):
    alice = pending_owner("alice")
    client = login(alice)
    assert client.get(TOKENS).status_code == 200
    page = _make(client, scopes=["read", "share"])
    assert page.status_code == 201
    assert "no-store" in page["Cache-Control"]
    key = re.search(r'data-testid="api-token-key">([^<]+)<', page.content.decode()).group(1)
    assert key.startswith("aro_")
    token = OwnerToken.objects.get()
    assert owner_token_by_key(key) == token
    assert (token.owner, token.name, token.scopes) == (alice, "nightly-export", ["read", "share"])
    assert timedelta(days=29) < token.expires_at - timezone.now() <= timedelta(days=30)
    assert key not in token.token_hash
    event = AccountEvent.objects.get()
    assert (event.kind, event.actor) == (AccountEvent.Kind.TOKEN_CREATED, alice.user)

    listing = client.get(TOKENS).content.decode()
    assert key not in listing
    assert token.token_prefix in listing
    assert "nightly-export" in listing


def test_making_a_token_needs_the_password_and_valid_choices(login, pending_owner):
    client = login(pending_owner("alice"))
    for fields in (
        {"password": "not my password"},
        {"password": ""},
        {"scopes": []},
        {"scopes": ["admin"]},
        {"expires_in_days": "3650"},
        {"expires_in_days": "-1"},
        {"name": "   "},
        {"name": "x" * 101},
    ):
        assert _make(client, **fields).status_code == 400, fields
    assert not OwnerToken.objects.exists()
    assert not AccountEvent.objects.exists()


def test_the_list_shows_scopes_state_and_last_use(login, pending_owner, make_owner_token):
    alice = pending_owner("alice")
    live, _ = make_owner_token(alice, scopes=("share",))
    used, _ = make_owner_token(alice)
    expired, _ = make_owner_token(alice)
    revoked, _ = make_owner_token(alice)
    OwnerToken.objects.filter(pk=used.pk).update(last_used_at=timezone.now())
    OwnerToken.objects.filter(pk=expired.pk).update(expires_at=timezone.now() - timedelta(days=1))
    owner_token_revoke(token=revoked, actor=alice.user)
    html = login(alice).get(TOKENS).content.decode()

    def row(token: OwnerToken) -> str:
        match = re.search(rf'<tr data-token-id="{token.pk}".*?</tr>', html, re.S)
        assert match, token
        return match.group(0)

    assert ">share<" in row(live)
    assert "never" in row(live)
    assert "never" not in row(used)
    assert "badge active" in row(live)
    assert ">expired<" in row(expired)
    assert ">revoked<" in row(revoked)
    assert 'data-testid="nav-api-tokens"' in html


def test_revoking_a_token_offers_its_grants_and_takes_them_back(
    login, make_owner, make_owner_token, django_capture_on_commit_callbacks
):
    alice, bob, carol = make_owner("alice"), make_owner("bob"), make_owner("carol")
    token, _ = make_owner_token(alice)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice, grantee=bob, made_with="token", made_with_token=token)
        grant_create(owner=alice, grantee=carol, made_with="session")
    client = login(alice)
    grants_page = client.get(reverse("grants")).content.decode()
    assert f'API token <a href="{reverse("api-token-revoke", args=[token.pk])}">' in grants_page
    assert token.name in grants_page
    assert "in the portal" in grants_page

    url = reverse("api-token-revoke", args=[token.pk])
    page = client.get(url).content.decode()
    assert 'data-grantee="bob"' in page
    assert 'data-grantee="carol"' not in page
    assert re.search(r'name="revoke_grants" value="yes" checked', page)
    assert "Also revoke this grant" in page

    with django_capture_on_commit_callbacks(execute=True):
        answer = client.post(url, {"revoke_grants": "yes"})
    assert answer.status_code == 302
    token.refresh_from_db()
    assert token.revoked_at is not None
    statuses = dict(Grant.objects.values_list("grantee__user__username", "status"))
    assert statuses == {"bob": Grant.Status.REVOKED, "carol": Grant.Status.ACTIVE}
    event = AccountEvent.objects.get(kind=AccountEvent.Kind.TOKEN_REVOKED)
    assert event.actor == alice.user
    assert "no live access" in client.get(url).content.decode().lower()


def test_another_owner_cannot_see_or_revoke_my_token(login, pending_owner, make_owner_token):
    alice, mallory = pending_owner("alice"), pending_owner("mallory")
    token, _ = make_owner_token(alice)
    client = login(mallory)
    url = reverse("api-token-revoke", args=[token.pk])
    assert client.get(url).status_code == 404
    assert client.post(url, {"revoke_grants": "yes"}).status_code == 404
    assert token.name not in client.get(TOKENS).content.decode()
    token.refresh_from_db()
    assert token.revoked_at is None


def test_revoking_needs_a_post_with_the_csrf_token(pending_owner, make_owner_token):
    alice = pending_owner("alice")
    token, _ = make_owner_token(alice)
    browser = Client(enforce_csrf_checks=True)
    browser.force_login(alice.user)
    url = reverse("api-token-revoke", args=[token.pk])
    assert browser.post(url, {"revoke_grants": "yes"}).status_code == 403
    token.refresh_from_db()
    assert token.revoked_at is None
