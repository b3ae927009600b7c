"""A single record's check asked of a real verify worker through Redis, without Celery's round
trip (sharing/verification/direct.py): the worker process checks and answers as the task does
(verified with the bytes it checked, tampered, no access), and once no worker serves, the view
falls back to the Celery task (here: unavailable, nothing shown)."""

import pytest

from sharing.errors import AccessDenied, IntegrityCheckFailed, VerificationUnavailable
from sharing.models import Record, SecurityEvent, Verdict
from sharing.services.uploads import record_create
from sharing.storage import envelope_storage
from sharing.verification.direct import direct_check_send, direct_checks_served
from sharing.verification.opening import record_open
from tests.support.harness import wait_for
from tests.support.tampering import tamper
from tests.support.worker_robots import registered_robots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]


def test_one_record_is_checked_by_the_worker_through_redis(worker_stack, settings):
    stack = worker_stack(workers=1)
    alice, bob = registered_robots(2)
    good = record_create(robot=alice.robot, data=alice.seal(1))
    changed = record_create(robot=alice.robot, data=alice.seal(2))
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == 2,
        timeout=120,
        what="both records anchored by the worker",
    )
    wait_for(direct_checks_served, timeout=60, what="the worker serving direct checks")

    # The worker answers the task's own answer, with the very bytes it checked.
    asked = direct_check_send([str(good.pk)], alice.owner.pk, "", None, None, None)
    assert asked is not None
    (answer,) = asked.get(timeout=60)
    assert (answer["record_id"], answer["outcome"]) == (str(good.pk), Verdict.Outcome.VERIFIED)
    verdict = Verdict.objects.get(pk=answer["verdict_id"])
    assert verdict.record_id == good.pk
    stored = envelope_storage().open(good.storage_name).read()
    assert answer["envelope"] is not None
    asked.forget()

    opened = record_open(record_id=good.pk, viewer=alice.owner)
    assert opened.verdict.outcome == Verdict.Outcome.VERIFIED
    assert opened.envelope == stored
    assert opened.header["seq"] == 1
    checks = Verdict.objects.filter(record=good).count()
    record_open(record_id=good.pk, viewer=alice.owner)
    assert Verdict.objects.filter(record=good).count() == checks + 1  # checked again, every view

    tamper(changed)
    with pytest.raises(IntegrityCheckFailed):
        record_open(record_id=changed.pk, viewer=alice.owner)
    assert Verdict.objects.filter(record=changed).latest("created_at").outcome == (
        Verdict.Outcome.TAMPERED
    )
    assert Record.objects.get(pk=changed.pk).tampered_at is not None
    assert SecurityEvent.objects.filter(owner=alice.owner).exists()

    with pytest.raises(AccessDenied):
        record_open(record_id=good.pk, viewer=bob.owner)

    settings.VERIFY_DIRECT = False  # the task, as before: the same answer
    assert record_open(record_id=good.pk, viewer=alice.owner).envelope == stored
    settings.VERIFY_DIRECT = True

    # Nobody serves any more: the view sends the task, which no worker takes here either.
    stack.kill_worker("w0")
    wait_for(lambda: not direct_checks_served(), timeout=30, what="the presence key expired")
    assert direct_check_send([str(good.pk)], alice.owner.pk, "", None, None, None) is None
    settings.VERIFY_TIMEOUT = 2
    with pytest.raises(VerificationUnavailable):
        record_open(record_id=good.pk, viewer=alice.owner)
