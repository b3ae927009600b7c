"""What the record list and the robot page say of their window's completeness (issue 44):
"n records, nothing missing", or each gap named (missing; deleted by the owner, when; removed by
retention, when) with a link to the records around it; a missing gap alerts the robot's owner
once, whoever's page found it.

Records are real uploads of a paired robot with their `topic_seq` set on the rows, as in
tests/api/test_completeness.py (whose helpers these are)."""

import re
from datetime import timedelta
from html import unescape

import pytest
from django.urls import reverse
from django.utils import timezone

from alerts.models import Alert, AlertCondition, AlertKind
from sharing.models import Record
from sharing.services.deletion import record_delete
from sharing.services.grants import grant_create
from tests.api.conftest import session_client
from tests.api.test_completeness import ODOM, lost, stream_upload

pytestmark = pytest.mark.django_db


@pytest.fixture
def alice(make_paired_robot):
    return make_paired_robot("alice")


@pytest.fixture
def odom(alice, upload):
    """Six records of /robot/odom half an hour ago: #2 lost, #3 deleted by alice."""
    made = stream_upload(upload, alice, 6)
    lost(made[2])
    record_delete(owner=alice.owner, record_id=made[3].pk, actor=alice.owner.user)
    return made


def _text(html: str, testid: str) -> str:
    found = re.search(rf'data-testid="{testid}"[^>]*>(.*?)</(p|li|div)>', html, re.S)
    assert found, testid
    return " ".join(unescape(re.sub(r"<[^>]+>", "", found.group(1))).split())


def _gaps(html: str) -> list[tuple[str, str]]:
    items = re.findall(r'<li data-testid="gap" data-reason="(\w+)".*?>(.*?)</li>', html, re.S)
    return [
        (reason, " ".join(unescape(re.sub(r"<[^>]+>", "", text)).split())) for reason, text in items
    ]


def _links(html: str) -> list[str]:
    return [unescape(link) for link in re.findall(r'href="([^"]+)" data-testid="gap-link"', html)]


def test_a_complete_window_says_nothing_is_missing(client, alice, upload):
    stream_upload(upload, alice, 6)
    client.force_login(alice.owner.user)
    html = client.get(reverse("records")).content.decode()
    assert _text(html, "completeness-summary") == (
        "In this selection (every page, any status): 6 records, nothing missing."
    )
    robot_page = client.get(reverse("robot-detail", args=[alice.robot.pk])).content.decode()
    assert _text(robot_page, "completeness-summary") == "Last hour: 6 records, nothing missing."
    assert not Alert.objects.filter(kind=AlertKind.RECORDS_MISSING).exists()


def test_the_record_list_names_each_gap_and_links_to_it(client, alice, odom):
    client.force_login(alice.owner.user)
    html = client.get(reverse("records")).content.decode()
    assert _text(html, "completeness-summary").startswith(
        "In this selection (every page, any status): 4 records, 1 missing, 2 gaps"
    )
    deleted_at = Record.objects.get(pk=odom[3].pk).deleted_at
    robot = alice.robot.name
    assert _gaps(html) == [
        ("missing", f"missing 1 record missing on {ODOM} of {robot} (#2): the records around it"),
        (
            "deleted",
            f"deleted 1 record deleted by the owner on {ODOM} of {robot} (#3), on "
            f"{deleted_at:%Y-%m-%d %H:%M:%S} UTC: the deleted records",
        ),
    ]
    assert "You are alerted once per gap" in _text(html, "completeness-missing-help")
    missing_link, deleted_link = _links(html)
    # Around the missing one: the records #1 (before) to #3 (after, deleted), to the second.
    around = client.get(missing_link).content.decode()
    ids = re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', around)
    assert ids == [str(odom[1].pk)]
    assert "topic #1" in around
    # The deleted one: the tombstone listed by the status filter "deleted".
    assert "status=deleted" in deleted_link
    tombstones = client.get(deleted_link).content.decode()
    ids = re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', tombstones)
    assert str(odom[3].pk) in ids


def test_more_records_missing_are_named_between_their_numbers(client, alice, upload):
    made = stream_upload(upload, alice, 8)
    for record in made[3:6]:
        lost(record)
    client.force_login(alice.owner.user)
    html = client.get(reverse("records"), {"topic": ODOM}).content.decode()
    (gap,) = _gaps(html)
    assert gap[1].startswith(f"missing 3 records missing on {ODOM} of ")
    assert "between #3 and #5" in gap[1]


def test_a_missing_gap_alerts_the_owner_once_whoever_finds_it(
    client, alice, odom, make_owner, django_capture_on_commit_callbacks
):
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    client.force_login(bob.user)
    shared = client.get(reverse("shared")).content.decode()
    assert [reason for reason, _ in _gaps(shared)] == ["missing", "deleted"]
    assert "Their owner is alerted." in _text(shared, "completeness-missing-help")
    (alert,) = Alert.objects.filter(kind=AlertKind.RECORDS_MISSING)
    assert alert.owner == alice.owner  # the robot's owner, not the grantee who looked
    assert alert.detail == {
        "robot": str(alice.robot.pk),
        "name": alice.robot.name,
        "topic": ODOM,
        "signer": alice.robot.key_hash,
        "from": 2,
        "to": 2,
    }
    assert "1 record of" in alert.summary
    assert "missing on /robot/odom (#2)" in alert.summary
    # Found again by the owner's list, robot page, API and series: no second alert.
    client.force_login(alice.owner.user)
    client.get(reverse("records"))
    client.get(reverse("robot-detail", args=[alice.robot.pk]))
    session_client(alice.owner).get("/api/v1/records/completeness/")
    assert Alert.objects.filter(kind=AlertKind.RECORDS_MISSING).count() == 1
    assert AlertCondition.objects.filter(kind=AlertKind.RECORDS_MISSING).count() == 1
    # A new gap is a new alert.
    lost(odom[4])
    client.get(reverse("records"))
    assert Alert.objects.filter(kind=AlertKind.RECORDS_MISSING).count() == 2


def test_the_robot_page_names_the_last_hours_gaps(client, alice, odom):
    client.force_login(alice.owner.user)
    html = client.get(reverse("robot-detail", args=[alice.robot.pk])).content.decode()
    section = html[html.index('id="robot-completeness"') :]
    section = section[: section.index("</section>\n\n")]
    assert _text(section, "completeness-summary").startswith("Last hour: 4 records, 1 missing")
    assert [reason for reason, _ in _gaps(section)] == ["missing", "deleted"]
    assert all(link.startswith(reverse("records") + "?robot=") for link in _links(section))
    # Records older than the hour are not in its count.
    Record.objects.filter(robot=alice.robot).update(captured_at=timezone.now() - timedelta(hours=2))
    later = client.get(reverse("robot-detail", args=[alice.robot.pk])).content.decode()
    assert "Nothing captured in the last hour." in later
    assert 'data-testid="gap"' not in later


def test_a_retention_gap_is_named_with_when(client, alice, upload):
    made = stream_upload(upload, alice, 4)
    swept = timezone.now()
    Record.objects.filter(pk__in=[made[0].pk, made[1].pk]).update(
        deleted_at=swept, deletion_reason=Record.Deletion.RETENTION
    )
    client.force_login(alice.owner.user)
    (gap,) = _gaps(client.get(reverse("records")).content.decode())
    assert gap == (
        "retention",
        f"retention 2 records removed by the retention policy on {ODOM} of {alice.robot.name} "
        f"between #0 and #1, on {swept:%Y-%m-%d %H:%M:%S} UTC: the deleted records",
    )


def test_a_window_too_long_for_a_page_says_so(client, alice, odom, monkeypatch):
    monkeypatch.setattr("sharing.views.completeness.COMPLETENESS_PAGE_MAX", 3)
    client.force_login(alice.owner.user)
    html = client.get(reverse("records")).content.decode()
    assert _text(html, "completeness-summary").startswith(
        "In this selection (every page, any status): 5 records, more than the 3 this page counts."
    )
    assert 'data-testid="gap"' not in html


def test_records_no_signer_counts_are_said_uncounted(client, alice, upload):
    for seq in (1, 2, 3):
        upload(alice, seq)  # signed as provenance v1: no topic_seq
    client.force_login(alice.owner.user)
    html = client.get(reverse("records")).content.decode()
    assert _text(html, "completeness-summary") == (
        "In this selection (every page, any status): 3 records, none of them counted by the "
        "robot (signed before provenance v2, or unsigned): whether any is missing cannot be told."
    )


def test_the_status_filter_is_no_gap(client, alice, odom):
    # Pending, anchored or tampered is how a record stands, not whether it is there: the
    # window's count is the same whatever the status asked for.
    client.force_login(alice.owner.user)
    for status in ("anchored", "pending", "tampered"):
        html = client.get(reverse("records"), {"status": status}).content.decode()
        assert [reason for reason, _ in _gaps(html)] == ["missing", "deleted"], status
