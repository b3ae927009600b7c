"""The owner's security page: what happened to the account and alarms about its records,
newest first, for that owner only; and the dashboard's notice of an operator's action."""

from datetime import timedelta

import pytest
from django.contrib.auth import get_user_model
from django.urls import reverse
from django.utils import timezone

from accounts.events import account_event_record
from accounts.models import AccountEvent
from accounts.services.owners import owner_active_set
from accounts.services.robots import robot_create
from sharing.errors import IntegrityCheckFailed
from sharing.models import SecurityEvent
from sharing.verification.opening import record_open
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db


@pytest.fixture
def operator_user(db):
    return get_user_model().objects.create_superuser("root", password="unused 1234 abcd")


def entries(html: str) -> int:
    return html.count('data-testid="security-event"')


def test_the_owner_sees_its_events_and_another_owner_does_not(
    client, login, pending_owner, operator_user
):
    alice, bob = pending_owner("alice"), pending_owner("bob")
    robot, _token = robot_create(owner=alice, name="arm")
    login(alice)
    client.post(reverse("robot-revoke", args=[robot.pk]))
    owner_active_set(owner=alice, active=False, actor=operator_user)
    owner_active_set(owner=alice, active=True, actor=operator_user)
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.FORGED_UPLOAD, owner=alice, detail={"robot": str(robot.pk)}
    )

    page = client.get(reverse("security"))
    assert page.status_code == 200
    html = page.content.decode()
    assert entries(html) == 4
    kinds = ["forged_upload", "admin_action", "robot_token_revoked"]
    positions = [html.index(f'data-kind="{kind}"') for kind in kinds]
    assert positions == sorted(positions)  # newest first
    assert "robot token revoked" in html
    assert ">you<" in html  # alice revoked her robot herself
    assert "operator root" in html
    assert html.count('data-by-operator="true"') == 2
    assert "upload refused as forged" in html
    assert 'data-testid="nav-security"' in html

    login(bob)
    html = client.get(reverse("security")).content.decode()
    assert entries(html) == 0
    assert 'data-testid="security-empty"' in html


def test_a_record_alarm_links_its_record(client, login, make_robot, upload):
    alice = make_robot("alice")
    record = upload(alice, 1)
    tamper(record)
    with pytest.raises(IntegrityCheckFailed):
        record_open(record_id=record.id, viewer=alice.owner)
    html = login(alice.owner).get(reverse("security")).content.decode()
    assert 'data-kind="tampered_on_view"' in html
    assert reverse("record-detail", args=[record.pk]) in html


def test_events_are_paged_fifty_at_a_time_across_both_kinds(client, login, pending_owner):
    owner = pending_owner()
    for number in range(60):
        account_event_record(
            owner=owner, kind=AccountEvent.Kind.TOKEN_CREATED, detail={"n": number}
        )
    SecurityEvent.objects.create(kind=SecurityEvent.Kind.FORGED_UPLOAD, owner=owner)
    login(owner)
    first = client.get(reverse("security")).content.decode()
    assert entries(first) == 50
    assert first.index('data-kind="forged_upload"') < first.index('data-kind="token_created"')
    assert "Page 1 of 2" in first
    second = client.get(reverse("security"), {"page": 2}).content.decode()
    assert entries(second) == 11
    assert '<dd class="hash">0</dd>' in second  # the oldest event is last
    assert "forged_upload" not in second
    assert client.get(reverse("security"), {"page": "nonsense"}).status_code == 200


def test_the_security_page_needs_an_owner(client, operator_user):
    assert client.get(reverse("security"))["Location"].startswith(reverse("login"))
    client.force_login(operator_user)
    assert client.get(reverse("security")).status_code == 403


def test_the_dashboard_points_to_an_operators_recent_action(
    client, login, pending_owner, operator_user
):
    owner = pending_owner()
    robot, _token = robot_create(owner=owner, name="arm")
    login(owner)
    client.post(reverse("robot-revoke", args=[robot.pk]))  # the owner's own: no notice
    assert 'data-testid="security-notice"' not in client.get(reverse("dashboard")).content.decode()

    owner_active_set(owner=owner, active=False, actor=operator_user)
    owner_active_set(owner=owner, active=True, actor=operator_user)
    login(owner)
    html = client.get(reverse("dashboard")).content.decode()
    assert 'data-testid="security-notice"' in html
    assert reverse("security") in html

    AccountEvent.objects.filter(owner=owner).update(created_at=timezone.now() - timedelta(days=8))
    assert 'data-testid="security-notice"' not in client.get(reverse("dashboard")).content.decode()
    SecurityEvent.objects.create(kind=SecurityEvent.Kind.FORGED_UPLOAD, owner=owner)
    assert 'data-testid="security-notice"' in client.get(reverse("dashboard")).content.decode()
