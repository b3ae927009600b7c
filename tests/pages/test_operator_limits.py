"""The operator is not the owner (finding F2): the admin console cannot set, reset or see an
owner's password, cannot make an owner's account staff, never shows a record's plaintext,
and what an operator does to an owner's account is on the owner's security page."""

import base64
import re
import uuid

import pytest
from django.contrib import admin
from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group, Permission
from django.test import Client
from django.urls import URLPattern, URLResolver, get_resolver, reverse

from accounts.models import AccountEvent, Owner
from sharing.services.grants import grant_create
from sharing.verification.opening import record_open
from smcrypto import sm4
from tests.pages.conftest import encrypted_key
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

NEW_PASSWORD = "operator picked this 99 x"


@pytest.fixture
def operator_user(db):
    return get_user_model().objects.create_superuser("root", password=TEST_PASSWORD)


@pytest.fixture
def admin_client(client, operator_user):
    """The operator, signed in through the admin's own sign-in page."""
    page = client.post(
        reverse("admin:login"), {"username": "root", "password": TEST_PASSWORD, "next": "/admin/"}
    )
    assert page.status_code == 302
    return client


def password_change_url(user: object) -> str:
    return reverse("admin:auth_user_password_change", args=[user.pk])


def user_change_url(user: object) -> str:
    return reverse("admin:auth_user_change", args=[user.pk])


def hash_fragments(user: object) -> list[str]:
    """The stored hash and the pieces the admin's hash summary would show (salt, hash)."""
    _algorithm, _iterations, salt, digest = user.password.split("$")
    return [user.password, salt[:6], digest[:6]]


def test_the_owner_password_change_page_is_refused(admin_client, pending_owner):
    owner = pending_owner()
    before = owner.user.password
    assert admin_client.get(password_change_url(owner.user)).status_code == 403
    page = admin_client.post(
        password_change_url(owner.user),
        {"password1": NEW_PASSWORD, "password2": NEW_PASSWORD, "usable_password": "true"},
    )
    assert page.status_code == 403
    owner.user.refresh_from_db()
    assert owner.user.password == before
    # The refused attempt (the POST, not the look) is on the owner's security page.
    (event,) = AccountEvent.objects.filter(owner=owner)
    assert event.kind == AccountEvent.Kind.ADMIN_ACTION
    assert "tried to set your password" in event.detail["action"]


def test_an_operators_password_is_still_managed_in_the_admin(admin_client, operator_user):
    other = get_user_model().objects.create_user("second-operator", password=TEST_PASSWORD)
    other.is_staff = True
    other.save()
    assert admin_client.get(password_change_url(other)).status_code == 200
    page = admin_client.post(
        password_change_url(other),
        {"password1": NEW_PASSWORD, "password2": NEW_PASSWORD, "usable_password": "true"},
    )
    assert page.status_code == 302
    other.refresh_from_db()
    assert other.check_password(NEW_PASSWORD)
    # The operator's own change form still links its password page and shows its summary.
    html = admin_client.get(user_change_url(operator_user)).content.decode()
    assert 'href="../password/"' in html
    assert hash_fragments(operator_user)[1] in html


def test_the_owner_change_form_shows_no_hash_and_no_password_link(admin_client, pending_owner):
    owner = pending_owner()
    page = admin_client.get(user_change_url(owner.user))
    assert page.status_code == 200
    html = page.content.decode()
    assert 'href="../password/"' not in html
    assert password_change_url(owner.user) not in html
    assert not any(fragment in html for fragment in hash_fragments(owner.user))
    for field in ("is_staff", "is_superuser", "groups", "user_permissions", "username"):
        assert f'name="{field}"' not in html, field
    assert 'name="is_active"' in html
    assert "This is an owner's account" in html


def test_posting_staff_superuser_groups_or_a_password_for_an_owner_changes_nothing(
    admin_client, pending_owner
):
    owner = pending_owner()
    before = get_user_model().objects.get(pk=owner.user.pk)
    group = Group.objects.create(name="operators")
    group.permissions.set(Permission.objects.all())
    page = admin_client.post(
        user_change_url(owner.user),
        {
            "username": "renamed",
            "password": "pbkdf2_sha256$1$salt$forged",
            "password1": NEW_PASSWORD,
            "password2": NEW_PASSWORD,
            "is_active": "on",
            "is_staff": "on",
            "is_superuser": "on",
            "groups": [str(group.pk)],
            "user_permissions": [str(p.pk) for p in Permission.objects.all()[:5]],
            "email": "operator@example.org",
            "last_login_0": "",
            "last_login_1": "",
            "date_joined_0": "2020-01-01",
            "date_joined_1": "00:00:00",
        },
    )
    assert page.status_code == 302
    after = get_user_model().objects.get(pk=owner.user.pk)
    assert (after.username, after.password, after.email) == (
        before.username,
        before.password,
        before.email,
    )
    assert not after.is_staff
    assert not after.is_superuser
    assert not after.groups.exists()
    assert not after.user_permissions.exists()
    assert after.is_active
    assert not AccountEvent.objects.filter(owner=owner).exists()  # nothing changed


def test_an_owner_cannot_be_deleted_from_the_admin(admin_client, pending_owner):
    owner = pending_owner()
    url = reverse("admin:auth_user_delete", args=[owner.user.pk])
    assert admin_client.get(url).status_code == 403
    assert admin_client.post(url, {"post": "yes"}).status_code == 403
    assert get_user_model().objects.filter(pk=owner.user.pk).exists()


def test_deactivating_an_owner_is_on_the_owners_security_page(
    admin_client, operator_user, pending_owner
):
    owner = pending_owner()
    page = admin_client.post(user_change_url(owner.user), {})  # is_active unticked
    assert page.status_code == 302
    owner.user.refresh_from_db()
    assert not owner.user.is_active
    event = AccountEvent.objects.get(owner=owner)
    assert event.kind == AccountEvent.Kind.ADMIN_ACTION
    assert event.actor == operator_user
    assert event.detail["action"] == "deactivated"
    # Deactivated: the owner cannot sign in.
    owner_client = Client()
    signin = {"username": owner.username, "password": TEST_PASSWORD}
    assert owner_client.post(reverse("login"), signin).status_code == 400

    admin_client.post(user_change_url(owner.user), {"is_active": "on"})
    owner.user.refresh_from_db()
    assert owner.user.is_active
    assert owner_client.post(reverse("login"), signin).status_code == 302
    html = owner_client.get(reverse("security")).content.decode()
    assert html.count('data-by-operator="true"') == 2
    assert "an operator changed the account" in html
    assert "deactivated" in html
    assert "reactivated" in html
    assert "operator root" in html


@pytest.fixture
def secret_record(make_robot, upload, django_capture_on_commit_callbacks):
    """A record whose plaintext holds a marker, opened by its owner and a grantee."""
    marker = f"PLAINTEXT-MARKER-{uuid.uuid4().hex}"
    alice = make_robot("alice")
    bob_setup = make_robot("bob")
    plaintext = f'{{"K": {{"note": "{marker}"}}}}'.encode()
    record = upload(alice, 1, plaintext=plaintext)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob_setup.owner)
    assert marker in record_open(record_id=record.id, viewer=bob_setup.owner).plaintext.decode()
    record_open(record_id=record.id, viewer=alice.owner)
    return alice, record, marker, plaintext


def admin_urls_of_every_row() -> list[str]:
    """Every registered model's changelist, and the change and history page of every row."""
    urls = [reverse("admin:index"), reverse("admin:chain-status")]
    for model, model_admin in admin.site._registry.items():
        opts = model._meta
        name = f"admin:{opts.app_label}_{opts.model_name}"
        urls.append(reverse(f"{name}_changelist"))
        for pk in model_admin.get_queryset(None).values_list("pk", flat=True):
            urls.append(reverse(f"{name}_change", args=[pk]))
            urls.append(reverse(f"{name}_history", args=[pk]))
    return urls


def test_no_admin_page_shows_a_records_plaintext(admin_client, secret_record):
    alice, record, marker, plaintext = secret_record
    forms = [
        base64.b64encode(plaintext).decode(),
        alice.key.hex(),
        alice.token,
    ]
    page = admin_client.post(
        reverse("admin:sharing_record_changelist"),
        {"action": "reverify", "_selected_action": [str(record.pk)]},
        follow=True,
    )
    assert "1 verified" in page.content.decode()
    assert marker not in page.content.decode()
    urls = admin_urls_of_every_row()
    assert reverse("admin:sharing_record_change", args=[record.pk]) in urls
    for url in urls:
        response = admin_client.get(url)
        assert response.status_code in (200, 503), url
        html = response.content.decode()
        assert marker not in html, url
        assert not any(secret in html for secret in forms), url


def test_an_operator_who_signs_in_cannot_open_owner_pages(client, operator_user, secret_record):
    _alice, record, marker, _plaintext = secret_record
    page = client.post(reverse("login"), {"username": "root", "password": TEST_PASSWORD})
    assert page.status_code == 302
    for url in (
        reverse("dashboard"),
        reverse("records"),
        reverse("shared"),
        reverse("security"),
        reverse("record-detail", args=[record.pk]),
        reverse("record-raw", args=[record.pk]),
        f"/api/v1/records/{record.pk}/content/",
    ):
        response = client.get(url)
        assert response.status_code in (401, 403), url
        assert marker not in response.content.decode(), url


def test_signing_in_as_the_owner_still_needs_the_owners_password(admin_client, pending_owner):
    """The operator tries every admin page that could set the owner's password."""
    owner = pending_owner()
    for data in (
        {"password1": NEW_PASSWORD, "password2": NEW_PASSWORD, "usable_password": "true"},
        {"usable_password": "false", "unset-password": "1"},
    ):
        admin_client.post(password_change_url(owner.user), data)
    admin_client.post(
        user_change_url(owner.user),
        {"is_active": "on", "password": NEW_PASSWORD, "password1": NEW_PASSWORD},
    )
    stranger = Client()
    guessed = {"username": owner.username, "password": NEW_PASSWORD}
    assert stranger.post(reverse("login"), guessed).status_code == 400
    assert stranger.get(reverse("dashboard")).status_code == 302
    original = {"username": owner.username, "password": TEST_PASSWORD}
    assert stranger.post(reverse("login"), original).status_code == 302
    assert stranger.get(reverse("dashboard")).status_code == 200


def test_there_is_no_route_to_sign_in_as_someone_else():
    def walk(patterns: list, prefix: str = "") -> list[str]:
        routes = []
        for pattern in patterns:
            if isinstance(pattern, URLResolver):
                routes += walk(pattern.url_patterns, prefix + str(pattern.pattern))
            elif isinstance(pattern, URLPattern):
                routes.append(prefix + str(pattern.pattern))
        return routes

    routes = walk(get_resolver().url_patterns)
    assert "admin/auth/user/<id>/password/" in routes
    suspicious = re.compile(r"impersonat|hijack|login[_-]?as|loginas|become|switch[_-]?user|su/")
    assert [route for route in routes if suspicious.search(route)] == []


def test_an_operator_registering_while_signed_in_stays_an_operator(admin_client, operator_user):
    page = admin_client.post(
        reverse("register"),
        {
            "username": "newcomer",
            "password1": TEST_PASSWORD,
            "password2": TEST_PASSWORD,
            "key_ciphertext": encrypted_key(sm4.generate_key()),
        },
    )
    assert page.status_code == 302
    assert not Owner.objects.filter(user=operator_user).exists()
    newcomer = get_user_model().objects.get(username="newcomer")
    assert Owner.objects.filter(user=newcomer).exists()
    assert not newcomer.is_staff
    assert not newcomer.is_superuser
