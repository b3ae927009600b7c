"""How long an anchoring run waits for its owner's batch to fill (sharing.services.anchoring):
until the uploads pause for ANCHOR_QUIET, at most until the oldest pending record is
ANCHOR_MAX_WAIT old.

The run's clock is a fake one: each sleep moves the records' times back by what was slept, as
time passing would, and may let new records arrive; no test waits for real.
"""

from collections.abc import Callable
from datetime import timedelta

import pytest
from django.db.models import F
from django.utils import timezone

from sharing.models import Record
from sharing.services import anchoring
from sharing.services.uploads import record_create

MAX_WAIT = 1.0
QUIET = 0.1


class FakeClock:
    """anchoring's `time`: sleeps that pass at once, records ageing by what was slept."""

    def __init__(self, owner_id: int, arrive: Callable[[], None] | None = None) -> None:
        self.owner_id = owner_id
        self.arrive = arrive
        self.now = 1000.0
        self.sleeps: list[float] = []

    def monotonic(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.sleeps.append(seconds)
        self.now += seconds
        Record.objects.filter(owner_id=self.owner_id).update(
            created_at=F("created_at") - timedelta(seconds=seconds)
        )
        if self.arrive is not None:
            self.arrive()


@pytest.fixture
def uploads(make_robot, settings, monkeypatch):
    settings.ANCHOR_MAX_WAIT = MAX_WAIT
    settings.ANCHOR_QUIET = QUIET
    setup = make_robot()
    seqs = iter(range(1, 10_000))

    def upload(count: int = 1, *, age: float = 0.0) -> None:
        for _ in range(count):
            record_create(robot=setup.robot, data=setup.seal(next(seqs)))
        if age:
            Record.objects.filter(owner=setup.owner).update(
                created_at=F("created_at") - timedelta(seconds=age)
            )

    def clock(arrive: Callable[[], None] | None = None) -> FakeClock:
        fake = FakeClock(setup.owner.pk, arrive)
        monkeypatch.setattr(anchoring, "time", fake)
        return fake

    upload.clock = clock
    upload.owner = setup.owner
    return upload


def test_a_batch_whose_uploads_paused_is_sent_at_once(uploads):
    uploads(3, age=2 * QUIET)
    clock = uploads.clock()
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    assert clock.sleeps == []


def test_a_batch_just_uploaded_waits_for_the_pause_not_for_max_wait(uploads):
    uploads(5)
    clock = uploads.clock()
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    assert 0 < sum(clock.sleeps) <= QUIET
    assert len(clock.sleeps) == 1


def test_a_steady_stream_is_batched_until_max_wait(uploads):
    """A new record after every sleep: never a pause, so the run takes what ANCHOR_MAX_WAIT
    gathered."""
    started = timezone.now()
    uploads(1)
    clock = uploads.clock(arrive=lambda: uploads(1))
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    # The records age by the fake sleeps and by the real time the uploads and queries took
    # (tenths of a second on a loaded machine): the run stops once both add up to MAX_WAIT.
    real = (timezone.now() - started).total_seconds()
    waited = sum(clock.sleeps)
    assert MAX_WAIT - QUIET - real < waited <= MAX_WAIT + 1e-6
    assert len(clock.sleeps) >= int((MAX_WAIT - real) / QUIET) - 1
    pending = Record.objects.filter(owner=uploads.owner, status=Record.Status.PENDING)
    assert pending.count() == 1 + len(clock.sleeps)  # every arrival is in the batch


def test_records_arriving_until_a_pause_share_the_batch(uploads):
    arrivals = iter([2, 2, 0])  # two records in each of the first two sleeps, then a pause
    uploads(1)
    clock = uploads.clock(arrive=lambda: uploads(next(arrivals, 0)))
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    assert len(clock.sleeps) == 3
    assert sum(clock.sleeps) < MAX_WAIT
    assert Record.objects.filter(owner=uploads.owner).count() == 5


def test_without_quiet_the_run_waits_max_wait_from_the_oldest(uploads, settings):
    settings.ANCHOR_QUIET = 0
    started = timezone.now()
    uploads(2, age=0.25)
    clock = uploads.clock()
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    real = (timezone.now() - started).total_seconds()  # the records aged by that too
    assert len(clock.sleeps) == 1
    assert MAX_WAIT - 0.25 - real <= clock.sleeps[0] <= MAX_WAIT - 0.25


def test_a_full_batch_or_none_waits_for_nothing(uploads, settings):
    clock = uploads.clock()
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)  # nothing pending
    settings.ANCHOR_BATCH_MAX = settings.ANCHOR_ROOT_MAX = 3
    uploads(3)
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    assert clock.sleeps == []


def test_records_timed_ahead_of_the_workers_clock_hold_a_run_max_wait_at_most(uploads):
    """A web host whose clock is an hour ahead: its records look newer than now forever; the
    run still waits ANCHOR_MAX_WAIT at most."""
    uploads(2, age=-3600)
    clock = uploads.clock()
    anchoring._wait_for_batch_to_fill(uploads.owner.pk)
    assert 0 < sum(clock.sleeps) <= MAX_WAIT + 1e-6
