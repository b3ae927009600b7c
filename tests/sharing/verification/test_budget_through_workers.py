"""The budget of integrity checks with a real Celery worker (sharing/verification/budget.py): a
read whose request stops waiting (its batch not answered in VERIFY_TIMEOUT, or its client gone
from the portal under gunicorn) leaves batches in the queue; the worker that takes them checks
none (counted by its verdicts and its log) and gives their records back to the caller's
budget."""

import re
from datetime import UTC, datetime, timedelta

import pytest
import requests

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
VERIFY_ENDED = re.compile(
    r"Task sharing\.tasks\.(?:records|series)_verify\[[^\]]+\] (succeeded|raised|retry)"
)
SKIPPED = "its read stopped waiting"


def _worker_skips(stack, *, batches: int) -> None:
    """A new worker (w1) takes `batches` queued check tasks, each ending without a check."""
    stack.start_worker("w1")
    log = stack.logs / "w1.log"
    wait_for(
        lambda: len(VERIFY_ENDED.findall(log.read_text())) >= batches,
        timeout=60,
        what=f"the worker to take the {batches} batches nobody waits for",
    )
    ended = [match.group(1) for match in VERIFY_ENDED.finditer(log.read_text())]
    assert ended == ["succeeded"] * batches
    assert log.read_text().count(SKIPPED) == batches


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
    _worker_skips(stack, batches=4)
    assert not Verdict.objects.exists()
    assert not Access.objects.exists()

    # Their 4 records came back to the budget (4 a day): the same read fits whole, and is checked.
    settings.VERIFY_TIMEOUT = 60
    again = records_open(
        records=records, viewer=setup.owner, kind=Access.Kind.PLOT, credential="session"
    )
    assert [result.verdict.outcome for result in again] == [Verdict.Outcome.VERIFIED] * 4
    assert Verdict.objects.count() == 4


def test_a_series_whose_client_goes_cancels_its_queued_checks(worker_stack, make_owner_token):
    stack = worker_stack(workers=1, env_overrides={"VERIFY_TIMEOUT": "120"})
    url = stack.start_web(workers=1)
    (setup,) = registered_robots(1)
    start = datetime.now(tz=UTC) - timedelta(minutes=1)
    for seq in range(1, 4):
        moment = (start + timedelta(seconds=seq)).isoformat().replace("+00:00", "Z")
        record_create(robot=setup.robot, data=setup.seal(seq, time=moment))
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == 3,
        timeout=60,
        what="3 records anchored",
    )

    # No worker takes checks now; the client gives up long before the portal would (120 s).
    stack.kill_worker("w0")
    _token, key = make_owner_token(setup.owner, scopes=("read",))
    query = {
        "robot": str(setup.robot.pk),
        "topic": "/robot/odom",
        "fields": "position.x",
        "since": start.isoformat(),
        "until": (start + timedelta(minutes=1)).isoformat(),
    }
    with pytest.raises(requests.Timeout):
        requests.get(
            f"{url}/api/v1/records/series/",
            params=query,
            headers={"Authorization": f"Token {key}"},
            timeout=3,
        )
    web_log = stack.logs / "web.log"
    wait_for(
        lambda: "the client closed its connection" in web_log.read_text(),
        timeout=60,
        what="the portal to see its client gone",
    )

    # A worker takes the queued batch: it checks none of it.
    _worker_skips(stack, batches=1)
    assert not Verdict.objects.exists()
