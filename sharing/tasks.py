"""Celery tasks of sharing: each loads by id and calls one service.

Anchoring and grants send transactions (the chain retry policy); the integrity check at view
time runs on the verify queue (portal/celery.py) with a short policy: a person is waiting.
"""

from datetime import timedelta
from typing import Any

from celery import current_app, shared_task, signals
from django.conf import settings

from accounts.errors import IdentityMismatch
from chainworker.errors import ChainUnavailable
from chainworker.work import CHAIN_TASK
from sharing import disk
from sharing.exports import run, withdraw
from sharing.services import anchoring, completeness, deletion, grant_chain, reconcile, sweep
from sharing.verification import budget, check, direct, series_check


@shared_task(name="sharing.tasks.records_anchor", **CHAIN_TASK)
def records_anchor(owner_id: int) -> int:
    return anchoring.records_anchor(owner_id=owner_id)


@shared_task(name="sharing.tasks.grant_sync", **CHAIN_TASK)
def grant_sync(grant_id: int) -> str:
    return grant_chain.grant_sync_on_chain(grant_id=grant_id).status


@shared_task(name="sharing.tasks.chain_work_sweep", soft_time_limit=60, time_limit=90)
def chain_work_sweep() -> dict[str, int]:
    return sweep.chain_work_sweep()


# Periodic (beat): it sends nothing itself but a redeployment on a reset development chain, and
# the next run repeats whatever one that failed did not finish, so it is never retried.
@shared_task(
    name="sharing.tasks.chain_reconcile", acks_late=True, soft_time_limit=600, time_limit=660
)
def chain_reconcile() -> dict[str, object]:
    return reconcile.chain_reconcile()


# Removing deleted records' ciphertext (queued after each deletion) and the retention policy
# (beat): idempotent, and the next run finishes what one cut short left, so never retried.
@shared_task(
    name="sharing.tasks.records_purge", acks_late=True, soft_time_limit=300, time_limit=360
)
def records_purge() -> int:
    return deletion.records_purge()


@shared_task(
    name="sharing.tasks.retention_apply", acks_late=True, soft_time_limit=600, time_limit=660
)
def retention_apply() -> dict[str, int]:
    return deletion.retention_apply()


# Robots' recent records read for gaps nobody has looked at (sharing/services/completeness.py).
@shared_task(name="sharing.tasks.records_missing_scan", soft_time_limit=300, time_limit=360)
def records_missing_scan() -> int:
    return completeness.records_missing_scan(
        window=timedelta(seconds=settings.COMPLETENESS_SCAN_WINDOW)
    )


# A view's check, on the verify queue; a refused identity is an answer, not a task failure.
VERIFY_TASK = {
    "autoretry_for": (ChainUnavailable,),
    "throws": (IdentityMismatch,),
    "retry_backoff": 1,
    "max_retries": 3,
    "soft_time_limit": 60,
    "time_limit": 90,
}


# One task for any number of records (a record page is one); `accesses` maps record owner ids
# (as text: JSON) to the Access the web process opened for its read, of `kind`; without it the
# worker opens the Access with the verdicts. `run_id` is the read's (verification/budget.py).
@shared_task(name="sharing.tasks.records_verify", **VERIFY_TASK)
def records_verify(
    record_ids: list[str],
    viewer_id: int,
    credential: str = "",
    token_id: int | None = None,
    accesses: dict[str, int] | None = None,
    kind: str | None = None,
    run_id: str | None = None,
) -> list[dict[str, Any]]:
    if not budget.check_run_wanted(run=run_id, caller_id=viewer_id, records=len(record_ids)):
        return []  # its read stopped waiting: nothing checked, the budget given back
    checked = check.records_verify(
        record_ids=record_ids,
        viewer_id=viewer_id,
        credential=credential,
        token_id=token_id,
        kind=kind,
        accesses=None if accesses is None else {int(k): v for k, v in accesses.items()},
    )
    return [check.verification_answer(one) for one in checked]


# A slice of a series' records checked, only the plotted numbers handed back, sealed for the
# web process under its wrapped answer key (sharing/verification/series_check.py).
@shared_task(name="sharing.tasks.series_verify", **VERIFY_TASK)
def series_verify(
    record_ids: list[str],
    viewer_id: int,
    credential: str,
    token_id: int | None,
    accesses: dict[str, int],
    fields: list[str],
    read_id: str,
    answer_key: str,
    part: int,
    run_id: str | None = None,
) -> dict[str, Any]:
    if not budget.check_run_wanted(run=run_id, caller_id=viewer_id, records=len(record_ids)):
        return {"verified": 0, "rows": None}  # its read stopped waiting: nothing checked
    return series_check.series_rows_check(
        record_ids=record_ids,
        viewer_id=viewer_id,
        credential=credential,
        token_id=token_id,
        accesses={int(k): v for k, v in accesses.items()},
        fields=fields,
        read_id=read_id,
        answer_key=answer_key,
        part=part,
    )


@signals.worker_process_init.connect
def direct_checks_start(**kwargs: object) -> None:
    """Each pool process of a worker that takes the verify queue also answers the web's
    single-record checks straight from Redis (sharing/verification/direct.py), with this
    task's own function."""
    queues = current_app.amqp.queues
    verify = current_app.conf.task_default_queue + current_app.conf.verify_queue_suffix
    consumed = queues.consume_from if queues.consume_from else queues
    if verify in consumed:
        direct.direct_checks_serving(records_verify.run)


# An export runs for as long as its records take; a message delivered twice finds it done.
@shared_task(name="sharing.tasks.export_run", acks_late=True, soft_time_limit=3600, time_limit=3660)
def export_run(export_id: str) -> str:
    return run.export_run(export_id=export_id).status


@shared_task(name="sharing.tasks.exports_sweep", soft_time_limit=600, time_limit=660)
def exports_sweep() -> dict[str, int]:
    return withdraw.exports_sweep()


@shared_task(name="sharing.tasks.exports_recheck", soft_time_limit=600, time_limit=660)
def exports_recheck(owner_id: int | None = None) -> int:
    return withdraw.exports_recheck(owner_id=owner_id)


@shared_task(name="sharing.tasks.disk_space_watch", soft_time_limit=30, time_limit=60)
def disk_space_watch() -> dict[str, int]:
    return disk.disk_space_watch()
