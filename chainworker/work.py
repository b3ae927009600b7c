"""What every piece of chain work shares, whichever app owns it: one worker at a time per
piece (a Redis lock), the error for work whose prerequisite is not on chain yet, and the
retry policy of the Celery tasks that run it."""

from collections.abc import Iterator
from contextlib import contextmanager

from celery.exceptions import SoftTimeLimitExceeded
from redis.lock import Lock

from chainworker.errors import (
    ChainUnavailable,
    InsufficientFunds,
    NonceError,
    TransactionDropped,
    TransactionTimeout,
)
from core.locks import lock_held
from core.redis_client import get_redis, redis_key


class ChainWorkNotReady(Exception):
    """What this work depends on is not on chain yet (e.g. the owner is not registered)."""


# What chain work shows while its sender cannot pay for gas (InsufficientFunds): it waits, it
# does not fail, and it uses up no attempt.
WAITING_FOR_GAS = (
    "waiting for gas: the owner's account cannot pay; the operator tops it up and it is sent "
    "again by itself"
)


@contextmanager
def exclusive(name: str, *, timeout: float = 60.0, wait: float = 30.0) -> Iterator[Lock]:
    """A Redis lock so only one worker does this piece of chain work at a time."""
    with lock_held(redis_key("work", name), client=get_redis(), timeout=timeout, wait=wait) as lock:
        if lock is None:
            raise ChainWorkNotReady(f"{name} is being worked on by another worker")
        yield lock


# Transient: the node, Redis or an earlier step is not there yet. Everything else fails loudly.
TRANSIENT = (
    ChainUnavailable,
    TransactionTimeout,
    TransactionDropped,
    NonceError,
    InsufficientFunds,
    ChainWorkNotReady,
    # A run cut short by the soft limit (a very slow node): what it sent is settled from the
    # chain by the next run, so running again is safe.
    SoftTimeLimitExceeded,
)
# The options of every task that sends transactions (`@shared_task(**CHAIN_TASK)`).
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
