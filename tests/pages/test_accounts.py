"""Registration, sign-in, lockout, password change, key rotation, and who may see what."""

import re

import pytest
from django.contrib.auth import get_user_model
from django.test import Client
from django.urls import reverse

from accounts.keyexchange import portal_sm2_public_key
from accounts.models import ChainState, Owner
from accounts.selectors import owner_key_bytes, owner_key_current
from smcrypto import key_id, sm4
from tests.pages.conftest import encrypted_key
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

OWNER_PAGES = [
    ("dashboard", {}),
    ("registration-progress", {}),
    ("account-status", {}),
    ("password_change", {}),
    ("key-rotation", {}),
    ("robots", {}),
    ("robot-config", {"robot_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
    ("records", {}),
    ("shared", {}),
    ("record-detail", {"record_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
    ("record-raw", {"record_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
    ("record-gallery", {"record_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
    ("grants", {}),
    ("audit", {}),
    ("record-delete", {"record_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
    ("records-delete", {}),
    ("account-delete", {}),
    ("robot-revoke", {"robot_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}),
]


@pytest.mark.parametrize(("name", "kwargs"), OWNER_PAGES)
def test_anonymous_is_sent_to_login(client, name, kwargs):
    url = reverse(name, kwargs=kwargs)
    page = client.get(url)
    assert page.status_code == 302
    assert page["Location"] == f"{reverse('login')}?next={url}"


def test_posts_of_anonymous_change_nothing(client):
    some_id = {"robot_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}
    for name, kwargs in [
        ("robot-revoke", some_id),
        ("robot-retention", some_id),
        ("record-delete", {"record_id": some_id["robot_id"]}),
        ("records-delete", {}),
        ("account-delete", {}),
    ]:
        assert client.post(reverse(name, kwargs=kwargs)).status_code == 302
    assert client.post(reverse("grant-revoke"), {"grantee": "x"}).status_code == 302
    assert client.post(reverse("grants"), {"grantee": "x"}).status_code == 302


def test_operator_without_owner_is_pointed_to_the_admin(client):
    admin = get_user_model().objects.create_superuser("root", password=TEST_PASSWORD)
    client.force_login(admin)
    page = client.get(reverse("dashboard"))
    assert page.status_code == 403
    assert "not an owner account" in page.content.decode()
    assert reverse("admin:index") in page.content.decode()
    assert client.get("/")["Location"] == reverse("admin:index")


@pytest.mark.parametrize(("name", "kwargs"), OWNER_PAGES)
def test_operator_without_owner_gets_403_on_every_owner_page(client, name, kwargs):
    client.force_login(get_user_model().objects.create_superuser("root", password=TEST_PASSWORD))
    page = client.get(reverse(name, kwargs=kwargs))
    assert page.status_code == 403
    assert "not an owner account" in page.content.decode()


@pytest.mark.parametrize(
    ("name", "kwargs", "form"),
    [
        ("robot-revoke", {"robot_id": "7c9e6679-7425-40de-944b-e07fc1f90ae7"}, {}),
        ("grants", {}, {"grantee": "bob"}),
        ("grant-revoke", {}, {"grantee": "bob"}),
        ("key-rotation", {}, {"password": TEST_PASSWORD}),
    ],
)
def test_operator_without_owner_gets_403_on_every_owner_form(client, name, kwargs, form):
    client.force_login(get_user_model().objects.create_superuser("root", password=TEST_PASSWORD))
    assert client.post(reverse(name, kwargs=kwargs), form).status_code == 403


# --- registration -----------------------------------------------------------------------


def test_register_page_never_submits_the_key_in_plaintext(client):
    page = client.get(reverse("register"))
    html = page.content.decode()
    assert page.status_code == 200
    assert f'data-sm2-public-key="{portal_sm2_public_key()}"' in html
    key_input = re.search(r"<input[^>]*id=\"id_sm4_key\"[^>]*>", html, re.S).group(0)
    assert "name=" not in key_input
    assert 'name="key_ciphertext"' in html
    assert "vendor/sm-crypto-0.3.13/sm2.js" in html
    assert "portal/keyexchange.js" in html
    assert "Registration needs JavaScript" in html  # <noscript>
    assert re.search(r'<button type="submit" id="register-submit"[^>]*disabled', html)


def test_register_logs_in_and_shows_progress_until_confirmed(
    client, deployed, django_capture_on_commit_callbacks
):
    key = sm4.generate_key()
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(
            reverse("register"),
            {
                "username": "alice",
                "password1": TEST_PASSWORD,
                "password2": TEST_PASSWORD,
                "key_ciphertext": encrypted_key(key),
            },
        )
    assert page.status_code == 302
    assert page["Location"] == reverse("registration-progress")
    owner = Owner.objects.get(user__username="alice")
    assert owner.chain_state == ChainState.CONFIRMED
    assert owner_key_bytes(owner_key_current(owner)) == key

    progress = client.get(reverse("registration-progress"))
    html = progress.content.decode()
    assert progress.status_code == 200
    assert "registered on chain" in html
    for tx in (owner.fund_tx, owner.enroll_tx, owner.register_tx):
        assert tx
        assert tx in html
    assert key.hex() not in html

    status = client.get(reverse("account-status")).json()
    assert status["chain_state"] == "confirmed"
    assert status["register_tx"] == owner.register_tx
    assert status["key"]["key_id"] == key_id(key).hex()
    assert key.hex() not in str(status)


def test_progress_page_polls_while_pending(client, pending_owner):
    owner = pending_owner("pat")
    client.force_login(owner.user)
    html = client.get(reverse("registration-progress")).content.decode()
    assert 'data-state="pending"' in html
    assert 'http-equiv="refresh"' in html  # without JavaScript
    assert "portal/progress.js" in html
    assert client.get(reverse("account-status")).json()["chain_state"] == "pending"


def _register_form(**overrides: str) -> dict[str, str]:
    form = {
        "username": "carol",
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(sm4.generate_key()),
    }
    form.update(overrides)
    return form


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"key_ciphertext": ""}, "needs JavaScript to encrypt the key"),
        ({"key_ciphertext": "04deadbeef"}, "could not be decrypted"),
        ({"password1": "1234", "password2": "1234"}, "This password is too short"),
        ({"password1": "password123", "password2": "password123"}, "too common"),
        ({"password2": "something else 99"}, "The two passwords differ"),
        ({"username": "no spaces allowed"}, "A username is made of ASCII letters"),
        ({"username": "\N{CYRILLIC SMALL LETTER A}lice"}, "A username is made of ASCII letters"),
    ],
)
def test_register_refuses_bad_input_and_creates_nothing(client, db, overrides, message):
    page = client.post(reverse("register"), _register_form(**overrides))
    assert page.status_code == 400
    assert message in page.content.decode()
    assert not get_user_model().objects.exists()
    assert not Owner.objects.exists()


def test_register_refuses_a_taken_username(client, pending_owner):
    pending_owner("carol")
    page = client.post(reverse("register"), _register_form())
    assert page.status_code == 400
    assert "This username is taken" in page.content.decode()
    assert Owner.objects.count() == 1


def test_register_refuses_an_all_zero_key(client, db):
    page = client.post(reverse("register"), _register_form(key_ciphertext=encrypted_key(bytes(16))))
    assert page.status_code == 400
    assert "all-zero" in page.content.decode()
    assert not Owner.objects.exists()


def test_register_keeps_the_encrypted_key_after_another_error(client, db):
    ciphertext = encrypted_key(sm4.generate_key())
    page = client.post(
        reverse("register"), _register_form(key_ciphertext=ciphertext, password2="differs 1234")
    )
    html = page.content.decode()
    assert f'value="{ciphertext}"' in html
    assert "The key from your previous attempt is kept" in html


def test_register_needs_csrf(db):
    client = Client(enforce_csrf_checks=True)
    page = client.post(reverse("register"), _register_form())
    assert page.status_code == 403
    assert not Owner.objects.exists()


# --- sign-in, lockout, sign-out -------------------------------------------------------


def test_login_and_logout(client, pending_owner):
    owner = pending_owner("dave")
    page = client.post(reverse("login"), {"username": "dave", "password": TEST_PASSWORD})
    assert page.status_code == 302
    assert page["Location"] == reverse("dashboard")
    assert client.get(reverse("robots")).status_code == 200
    assert client.get(reverse("logout")).status_code == 405  # sign-out is a POST
    assert client.post(reverse("logout")).status_code == 302
    assert client.get(reverse("robots")).status_code == 302
    assert owner.user.is_active


def test_login_goes_to_next(client, pending_owner):
    pending_owner("dave")
    page = client.post(
        reverse("login") + "?next=/grants/",
        {"username": "dave", "password": TEST_PASSWORD, "next": "/grants/"},
    )
    assert page["Location"] == "/grants/"


def test_login_with_a_wrong_password(client, pending_owner):
    pending_owner("dave")
    page = client.post(reverse("login"), {"username": "dave", "password": "wrong"})
    assert page.status_code == 400
    assert "Please enter a correct username and password" in page.content.decode()
    assert client.get(reverse("dashboard")).status_code == 302


def test_lockout_after_repeated_bad_logins(client, pending_owner, settings):
    pending_owner("erin")
    for _ in range(settings.AXES_FAILURE_LIMIT - 1):
        page = client.post(reverse("login"), {"username": "erin", "password": "guess"})
        assert page.status_code == 400
    page = client.post(reverse("login"), {"username": "erin", "password": "guess"})
    assert page.status_code == 429
    assert "Too many failed sign-in attempts" in page.content.decode()
    # Locked out: even the right password is refused now.
    page = client.post(reverse("login"), {"username": "erin", "password": TEST_PASSWORD})
    assert page.status_code == 429
    assert "15 minutes" in page.content.decode()
    assert client.get(reverse("dashboard")).status_code == 302


def test_password_change(client, pending_owner):
    owner = pending_owner("fay")
    client.force_login(owner.user)
    url = reverse("password_change")
    assert client.get(url).status_code == 200
    refused = client.post(
        url,
        {
            "old_password": "wrong",
            "new_password1": "a new pass 9876",
            "new_password2": "a new pass 9876",
        },
    )
    assert refused.status_code == 200
    assert "Your old password was entered incorrectly" in refused.content.decode()
    done = client.post(
        url,
        {
            "old_password": TEST_PASSWORD,
            "new_password1": "a new pass 9876",
            "new_password2": "a new pass 9876",
        },
        follow=True,
    )
    assert "Your password was changed" in done.content.decode()
    owner.user.refresh_from_db()
    assert owner.user.check_password("a new pass 9876")


# --- key rotation -----------------------------------------------------------------------


def test_key_rotation(client, make_owner, django_capture_on_commit_callbacks):
    owner = make_owner("gus")
    old_key = owner_key_current(owner)
    client.force_login(owner.user)
    page = client.get(reverse("key-rotation"))
    assert page.status_code == 200
    assert old_key.key_id in page.content.decode()

    new_key = sm4.generate_key()
    with django_capture_on_commit_callbacks(execute=True):
        done = client.post(
            reverse("key-rotation"),
            {"password": TEST_PASSWORD, "key_ciphertext": encrypted_key(new_key)},
        )
    assert done.status_code == 302
    html = client.get(done["Location"]).content.decode()
    current = owner_key_current(owner)
    assert current.key_id == key_id(new_key).hex()
    assert current.chain_state == ChainState.CONFIRMED
    assert current.tx_hash in html
    assert f"Your new key {current.key_id} is in use" in html
    assert new_key.hex() not in html

    again = client.post(
        reverse("key-rotation"),
        {"password": TEST_PASSWORD, "key_ciphertext": encrypted_key(new_key)},
    )
    assert again.status_code == 400
    assert "used by this owner before" in again.content.decode()


@pytest.mark.parametrize(
    ("form", "message"),
    [
        ({"password": "wrong"}, "This is not your password"),
        ({"password": TEST_PASSWORD, "key_ciphertext": ""}, "needs JavaScript"),
        ({"password": TEST_PASSWORD, "key_ciphertext": "zz"}, "could not be decrypted"),
    ],
)
def test_key_rotation_refusals_change_nothing(client, pending_owner, form, message):
    owner = pending_owner()
    before = owner_key_current(owner).key_id
    client.force_login(owner.user)
    form.setdefault("key_ciphertext", encrypted_key(sm4.generate_key()))
    page = client.post(reverse("key-rotation"), form)
    assert page.status_code == 400
    assert message in page.content.decode()
    assert owner_key_current(owner).key_id == before
    assert owner.keys.count() == 1


# --- landing page -----------------------------------------------------------------------


def test_landing_page_sends_owners_to_their_dashboard(client, pending_owner):
    assert client.get("/")["Location"] == reverse("login")
    client.force_login(pending_owner().user)
    page = client.get("/")
    assert page.status_code == 302
    assert page["Location"] == reverse("dashboard")
