"""The integrity check at view time, run by the worker."""

from celery import shared_task

from chainworker.chain import ChainUnavailable
from sharing import services


@shared_task(
    name="sharing.tasks.record_verify",
    autoretry_for=(ChainUnavailable,),
    retry_backoff=1,
    max_retries=3,
    soft_time_limit=60,
    time_limit=90,
)
def record_verify(record_id: str, viewer_id: int) -> dict[str, object]:
    verification = services.record_verify(record_id=record_id, viewer_id=viewer_id)
    return {"verdict_id": verification.verdict.pk, "outcome": verification.verdict.outcome}
