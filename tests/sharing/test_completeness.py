"""Every record counted (sharing/selectors/completeness.py): per stream (signer, topic) the first
and last topic_seq of a window, its count, and every gap with the portal's reason.

Rows are made here as the stream index sees them (signer, topic, topic_seq, tombstones), as
the other selector tests make theirs: the reading is of rows, whatever stored them."""

import uuid
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from accounts.services.robots import robot_create
from sharing.models import Record
from sharing.selectors.completeness import (
    GAP_DELETED,
    GAP_MISSING,
    GAP_RETENTION,
    Gap,
    record_streams,
)
from tests.pages.conftest import pending_owner  # noqa: F401  (the fixture)

pytestmark = pytest.mark.django_db

SIGNER = "a" * 64
OTHER_SIGNER = "b" * 64
T0 = datetime(2026, 11, 30, 12, 0, tzinfo=UTC)


@pytest.fixture
def robot(pending_owner):  # noqa: F811
    owner = pending_owner()
    made, _token = robot_create(owner=owner, name=f"robot-{uuid.uuid4().hex[:6]}")
    return made


def row(robot, topic_seq, *, topic="/odom", signer=SIGNER, deleted=None, reason="", seq=None):
    """One record row of `robot`: captured a second apart by topic_seq, as a robot sends."""
    return Record.objects.create(
        owner=robot.owner,
        robot=robot,
        topic=topic,
        data_type="nav_msgs/Odometry",
        seq=seq if seq is not None else Record.objects.filter(robot=robot).count() + 1,
        captured_at=T0 + timedelta(seconds=topic_seq or 0),
        key_id="00" * 8,
        digest=uuid.uuid4().hex * 2,
        signer=signer,
        topic_seq=topic_seq,
        size=100,
        storage_name=f"test/{uuid.uuid4().hex}",
        deleted_at=deleted,
        deletion_reason=reason,
    )


def rows(robot, numbers, **kwargs):
    return [row(robot, n, **kwargs) for n in numbers]


def streams_of(robot):
    return record_streams(Record.objects.filter(robot=robot))


def test_consecutive_numbers_are_one_stream_without_gaps(robot):
    rows(robot, range(5, 15))
    completeness = streams_of(robot)
    (stream,) = completeness.streams
    assert (stream.signer, stream.topic, stream.robot_id) == (SIGNER, "/odom", str(robot.pk))
    assert (stream.first, stream.last, stream.count, stream.gaps) == (5, 14, 10, ())
    assert stream.complete
    assert (completeness.missing, completeness.uncounted) == (0, 0)
    assert completeness.as_json() == {
        "streams": [
            {
                "signer": SIGNER,
                "topic": "/odom",
                "robot": str(robot.pk),
                "first": 5,
                "last": 14,
                "count": 10,
                "gaps": [],
            }
        ],
        "uncounted": 0,
    }


def test_a_complete_window_is_one_aggregate_and_one_count(robot):
    rows(robot, range(50))
    with CaptureQueriesContext(connection) as queries:
        streams_of(robot)
    assert len(queries) == 2  # the streams' spans, the uncounted records: no row read


def test_rows_deleted_behind_the_portals_back_are_missing(robot):
    made = rows(robot, range(10))
    # Gone from the database, no tombstone: no owner's action explains them.
    Record.objects.filter(pk__in=[made[3].pk, made[4].pk, made[5].pk]).delete()
    Record.objects.filter(pk=made[8].pk).delete()
    (stream,) = streams_of(robot).streams
    assert (stream.first, stream.last, stream.count) == (0, 9, 6)
    assert stream.gaps == (Gap(3, 5, GAP_MISSING), Gap(8, 8, GAP_MISSING))
    assert stream.missing == 4
    assert [gap.as_json() for gap in stream.gaps] == [
        {"from": 3, "to": 5, "reason": "missing"},
        {"from": 8, "to": 8, "reason": "missing"},
    ]
    assert [s for s in streams_of(robot).streams if s.missing] == [stream]


def test_an_owners_deletion_is_named_deleted_with_when(robot):
    when = T0 + timedelta(days=1)
    rows(robot, range(3))
    row(robot, 3, deleted=when, reason=Record.Deletion.OWNER)
    row(robot, 4, deleted=when + timedelta(minutes=5), reason=Record.Deletion.OWNER)
    rows(robot, range(5, 7))
    completeness = streams_of(robot)
    (stream,) = completeness.streams
    assert (stream.first, stream.last, stream.count) == (0, 6, 5)
    # Two deletions side by side are one gap, at the latest of them.
    assert stream.gaps == (Gap(3, 4, GAP_DELETED, when + timedelta(minutes=5)),)
    assert stream.gaps[0].as_json() == {
        "from": 3,
        "to": 4,
        "reason": "deleted",
        "at": (when + timedelta(minutes=5)).isoformat(),
    }
    assert completeness.missing == 0
    assert not [s for s in completeness.streams if s.missing]


def test_a_retention_sweep_is_named_retention_with_when(robot):
    swept = T0 + timedelta(days=30)
    rows(robot, range(4), deleted=swept, reason=Record.Deletion.RETENTION)
    rows(robot, range(4, 6))
    (stream,) = streams_of(robot).streams
    assert (stream.first, stream.last, stream.count) == (0, 5, 2)
    assert stream.gaps == (Gap(0, 3, GAP_RETENTION, swept),)


def test_gaps_that_touch_are_joined_by_reason_and_kept_apart_across_reasons(robot):
    when = T0 + timedelta(days=2)
    row(robot, 0)
    row(robot, 1, deleted=when, reason=Record.Deletion.OWNER)
    # An account's deletion is the owner's too: one "deleted" gap with the record before.
    row(robot, 2, deleted=when + timedelta(hours=1), reason=Record.Deletion.ACCOUNT)
    # 3 and 4: no row (missing), right after the deletion: a gap of its own.
    row(robot, 5, deleted=when, reason=Record.Deletion.RETENTION)
    row(robot, 6)
    (stream,) = streams_of(robot).streams
    assert stream.gaps == (
        Gap(1, 2, GAP_DELETED, when + timedelta(hours=1)),
        Gap(3, 4, GAP_MISSING),
        Gap(5, 5, GAP_RETENTION, when),
    )


def test_a_window_counts_what_lies_in_it_and_its_ends_are_its_own(robot):
    made = rows(robot, range(10))
    Record.objects.filter(pk=made[6].pk).delete()
    window = Record.objects.filter(
        robot=robot,
        captured_at__gte=T0 + timedelta(seconds=2),
        captured_at__lt=T0 + timedelta(seconds=8),
    )
    (stream,) = record_streams(window).streams
    assert (stream.first, stream.last, stream.count) == (2, 7, 5)
    assert stream.gaps == (Gap(6, 6, GAP_MISSING),)
    # A window that ends before the gap sees none.
    (before,) = record_streams(window.filter(captured_at__lt=T0 + timedelta(seconds=6))).streams
    assert (before.first, before.last, before.gaps) == (2, 5, ())


def test_each_signer_and_topic_is_a_stream_of_its_own(robot):
    rows(robot, range(3), topic="/odom")
    rows(robot, [0, 2], topic="/scan")
    # A new key of the same robot starts again at 0: its numbers are not the old key's.
    rows(robot, range(2), topic="/odom", signer=OTHER_SIGNER)
    completeness = streams_of(robot)
    summary = [
        (s.signer[0], s.topic, s.first, s.last, s.count, s.gaps) for s in completeness.streams
    ]
    assert summary == [
        ("a", "/odom", 0, 2, 3, ()),
        ("a", "/scan", 0, 2, 2, (Gap(1, 1, GAP_MISSING),)),
        ("b", "/odom", 0, 1, 2, ()),
    ]
    assert (completeness.counted, completeness.gaps, completeness.missing) == (7, 1, 1)


def test_v1_and_unsigned_records_are_uncounted(robot):
    rows(robot, range(2))
    row(robot, None, signer="")  # unsigned: a robot added by hand
    row(robot, None)  # v1: signed, no topic_seq
    row(robot, None, deleted=T0, reason=Record.Deletion.OWNER)  # a deleted one is no record
    completeness = streams_of(robot)
    assert completeness.uncounted == 2
    assert [(s.first, s.last, s.count) for s in completeness.streams] == [(0, 1, 2)]
    assert completeness.as_json()["uncounted"] == 2


def test_nothing_in_the_window_is_no_stream(robot):
    completeness = streams_of(robot)
    assert completeness.as_json() == {"streams": [], "uncounted": 0}
