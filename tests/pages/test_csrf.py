"""Forms that change something refuse a POST without the page's CSRF token, and change nothing.

Each test also sends the same form with the token, so the refusal is known to be the CSRF
check's and not some other.
"""

import pytest
from django.test import Client
from django.urls import reverse

from accounts.selectors import owner_key_current
from accounts.services.robots import robot_create
from smcrypto import sm4
from tests.pages.conftest import encrypted_key
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

NEW_PASSWORD = "another pass phrase 77"


@pytest.fixture
def csrf_client() -> Client:
    return Client(enforce_csrf_checks=True)


def _token(client: Client, page: str) -> str:
    """The CSRF token of the form on `page`, as the browser would send it."""
    assert client.get(page).status_code == 200
    return client.cookies["csrftoken"].value


def test_key_rotation_needs_csrf(csrf_client, pending_owner):
    owner = pending_owner()
    before = owner_key_current(owner).key_id
    csrf_client.force_login(owner.user)
    form = {"password": TEST_PASSWORD, "key_ciphertext": encrypted_key(sm4.generate_key())}
    page = csrf_client.post(reverse("key-rotation"), form)
    assert page.status_code == 403
    assert "security token (CSRF)" in page.content.decode()
    assert owner_key_current(owner).key_id == before
    assert owner.keys.count() == 1

    form["csrfmiddlewaretoken"] = _token(csrf_client, reverse("key-rotation"))
    assert csrf_client.post(reverse("key-rotation"), form).status_code == 302
    assert owner_key_current(owner).key_id != before


def test_password_change_needs_csrf(csrf_client, pending_owner):
    owner = pending_owner()
    csrf_client.force_login(owner.user)
    form = {
        "old_password": TEST_PASSWORD,
        "new_password1": NEW_PASSWORD,
        "new_password2": NEW_PASSWORD,
    }
    page = csrf_client.post(reverse("password_change"), form)
    assert page.status_code == 403
    owner.user.refresh_from_db()
    assert owner.user.check_password(TEST_PASSWORD)

    form["csrfmiddlewaretoken"] = _token(csrf_client, reverse("password_change"))
    assert csrf_client.post(reverse("password_change"), form).status_code == 302
    owner.user.refresh_from_db()
    assert owner.user.check_password(NEW_PASSWORD)


def test_robot_token_revoke_needs_csrf(csrf_client, pending_owner):
    owner = pending_owner()
    robot, _token_value = robot_create(owner=owner, name="r1")
    csrf_client.force_login(owner.user)
    url = reverse("robot-revoke", args=[robot.id])
    page = csrf_client.post(url)
    assert page.status_code == 403
    robot.refresh_from_db()
    assert robot.is_active

    token = _token(csrf_client, reverse("robots"))
    assert csrf_client.post(url, {"csrfmiddlewaretoken": token}).status_code == 302
    robot.refresh_from_db()
    assert not robot.is_active


def test_login_needs_csrf(csrf_client, pending_owner):
    owner = pending_owner()
    form = {"username": owner.username, "password": TEST_PASSWORD}
    page = csrf_client.post(reverse("login"), form)
    assert page.status_code == 403
    assert csrf_client.get(reverse("dashboard")).status_code == 302  # still signed out

    form["csrfmiddlewaretoken"] = _token(csrf_client, reverse("login"))
    page = csrf_client.post(reverse("login"), form)
    assert page.status_code == 302
    assert page["Location"] == reverse("dashboard")
    assert csrf_client.get(reverse("dashboard")).status_code == 200
