"""Celery tasks for chain work: each loads by id, calls one service and declares its retries."""

from celery import shared_task
from celery.exceptions import SoftTimeLimitExceeded

from chainworker import services
from chainworker.chain import ChainUnavailable, InsufficientFunds, NonceError, TransactionTimeout

# Transient: the node, Redis or an earlier step is not there yet. Everything else fails loudly.
TRANSIENT = (
    ChainUnavailable,
    TransactionTimeout,
    NonceError,
    InsufficientFunds,
    services.ChainWorkNotReady,
    # A run cut short by the soft limit (a very slow node): what it sent is settled from the
    # chain by the next run, so running again is safe.
    SoftTimeLimitExceeded,
)
CHAIN_TASK = {
    "autoretry_for": TRANSIENT,
    "retry_backoff": 1,
    "retry_backoff_max": 60,
    "retry_jitter": True,
    "max_retries": 50,
    "acks_late": True,
    "soft_time_limit": 600,
    "time_limit": 660,
}


@shared_task(name="chainworker.tasks.owner_register", **CHAIN_TASK)
def owner_register(owner_id: int) -> str:
    return services.owner_register_on_chain(owner_id=owner_id).chain_state


@shared_task(name="chainworker.tasks.key_rotate", **CHAIN_TASK)
def key_rotate(owner_key_id: int) -> str:
    return services.key_rotate_on_chain(owner_key_id=owner_key_id).chain_state


@shared_task(name="chainworker.tasks.grant_sync", **CHAIN_TASK)
def grant_sync(grant_id: int) -> str:
    return services.grant_sync_on_chain(grant_id=grant_id).status


@shared_task(name="chainworker.tasks.records_anchor", **CHAIN_TASK)
def records_anchor(owner_id: int) -> int:
    return services.records_anchor(owner_id=owner_id)


@shared_task(name="chainworker.tasks.sweep_stale", soft_time_limit=60, time_limit=90)
def sweep_stale() -> dict[str, int]:
    return services.sweep_stale()
