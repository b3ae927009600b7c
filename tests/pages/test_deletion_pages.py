"""The pages of retention and deletion: a robot's retention, the selection to delete, and
deleting the account (password again, everything explained first)."""

import pytest
from django.urls import reverse

from accounts.models import AccountEvent, Robot
from accounts.services.robots import robot_create
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


def test_a_robots_retention_is_set_and_cleared_on_the_robots_page(login, pending_owner):
    owner = pending_owner()
    robot, _ = robot_create(owner=owner, name="r1")
    client = login(owner)
    url = reverse("robot-retention", args=[robot.id])
    page = client.post(url, {"retention_days": "30"}, follow=True)
    assert "kept 30 days after capture" in page.content.decode()
    assert 'value="30"' in page.content.decode()  # shown in the robot's row
    assert Robot.objects.get(pk=robot.pk).retention_days == 30
    event = AccountEvent.objects.get(owner=owner, kind=AccountEvent.Kind.RETENTION_SET)
    assert event.detail == {"robot": "r1", "before": "forever", "now": "30 days"}
    for wrong in ("0", "-3", "abc", "36501", "1e9"):
        page = client.post(url, {"retention_days": wrong}, follow=True)
        assert page.status_code == 200
        assert "Retention of r1 unchanged" in page.content.decode(), wrong
        assert Robot.objects.get(pk=robot.pk).retention_days == 30
    assert "until you delete them" in client.post(url, {}, follow=True).content.decode()
    assert Robot.objects.get(pk=robot.pk).retention_days is None
    # Another owner's robot is out of reach.
    login(pending_owner())
    assert client.post(url, {"retention_days": "1"}).status_code == 404
    assert Robot.objects.get(pk=robot.pk).retention_days is None


def test_deleting_records_needs_a_selection(login, pending_owner):
    client = login(pending_owner())
    assert client.get(reverse("records-delete")).status_code == 200
    for method in (client.get, client.post):
        page = method(reverse("records-delete"), {"robot": "", "topic": ""})
        assert page.status_code == 400
        assert "Choose a robot, a topic or a time range" in page.content.decode()
    assert client.get(reverse("records-delete"), {"since": "yesterday"}).status_code == 400


def test_deleting_the_account_explains_and_needs_the_password(login, pending_owner):
    owner = pending_owner()
    client = login(owner)
    security = client.get(reverse("security")).content.decode()
    assert reverse("account-delete") in security
    page = client.get(reverse("account-delete")).content.decode()
    for said in ("On chain, forever", owner.eoa_address, "stays reserved", "cannot be undone"):
        assert said in page
    for form in (
        {"password": "wrong password", "understood": "on"},
        {"password": TEST_PASSWORD},  # not ticked
    ):
        assert client.post(reverse("account-delete"), form).status_code == 400
        owner.user.refresh_from_db()
        assert owner.user.is_active
    done = client.post(reverse("account-delete"), {"password": TEST_PASSWORD, "understood": "on"})
    assert done.status_code == 200
    assert "is deleted and you are signed out" in done.content.decode()
    owner.refresh_from_db()
    assert owner.deleted_at is not None
    assert not owner.user.is_active
    # Signed out, and the password no longer signs in.
    assert client.get(reverse("dashboard")).status_code == 302
    answer = client.post(reverse("login"), {"username": owner.username, "password": TEST_PASSWORD})
    assert answer.status_code != 302
