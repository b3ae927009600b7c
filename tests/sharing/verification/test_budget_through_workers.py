"""The budget of integrity checks with a real Celery worker (sharing/verification/budget.py): a
read whose request stops waiting (its batch not answered in VERIFY_TIMEOUT) leaves batches in
the queue; the worker that takes them checks none (counted by its verdicts and its log) and
gives their records back to the caller's budget."""

import re

import pytest

from sharing.errors import VerificationUnavailable
from sharing.models import Access, Record, Verdict
from sharing.services.uploads import record_create
from sharing.verification import opening
from sharing.verification.opening import records_open
from tests.support.harness import wait_for
from tests.support.worker_robots import registered_robots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]

# A check task's end in the worker's log (Celery's own lines; results are not logged).
VERIFY_ENDED = re.compile(r"Task sharing\.tasks\.records_verify\[[^\]]+\] (succeeded|raised|retry)")
SKIPPED = "its read stopped waiting"


def test_a_read_that_stops_waiting_cancels_its_queued_checks(worker_stack, settings, monkeypatch):
    # The worker's budget is the test process's: what it gives back is counted alike.
    stack = worker_stack(workers=1, env_overrides={"CHECK_BUDGET": "4/day"})
    settings.CHECK_BUDGET = "4/day"
    (setup,) = registered_robots(1)
    records = [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in range(1, 5)]
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == 4,
        timeout=60,
        what="4 records anchored",
    )

    # No worker takes checks now: the read's 4 batches wait in the queue, and it gives up.
    stack.kill_worker("w0")
    settings.VERIFY_TIMEOUT = 2
    monkeypatch.setattr(opening, "VERIFY_BATCH", 1)
    results = records_open(
        records=records, viewer=setup.owner, kind=Access.Kind.PLOT, credential="session"
    )
    assert all(isinstance(result, VerificationUnavailable) for result in results)

    # A worker takes the queued batches: it checks none of them.
    stack.start_worker("w1")
    log = stack.logs / "w1.log"
    wait_for(
        lambda: len(VERIFY_ENDED.findall(log.read_text())) >= 4,
        timeout=60,
        what="the worker to take the 4 batches nobody waits for",
    )
    ended = [match.group(1) for match in VERIFY_ENDED.finditer(log.read_text())]
    assert ended == ["succeeded"] * 4
    assert log.read_text().count(SKIPPED) == 4
    assert not Verdict.objects.exists()
    assert not Access.objects.exists()

    # Their 4 records came back to the budget (4 a day): the same read fits whole, and is checked.
    settings.VERIFY_TIMEOUT = 60
    again = records_open(
        records=records, viewer=setup.owner, kind=Access.Kind.PLOT, credential="session"
    )
    assert [result.verdict.outcome for result in again] == [Verdict.Outcome.VERIFIED] * 4
    assert Verdict.objects.count() == 4
