"""Redis locks: one piece of work done by one process at a time, across every web and worker
process (redis-py's Lock: a key with a token and a timeout, so a holder that dies frees it).

`lock_held` takes the lock, waiting at most `wait` seconds, and always releases it; `lock_renew`
extends a hold that a long run keeps alive between its steps, and `renew_every` does that from
a thread for a run that has no steps to do it in. A hold lost meanwhile (expired, Redis gone) is
never an error at release: the lock's timeout frees it for the next holder.
"""

import logging
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress

from redis import Redis
from redis.exceptions import LockError, RedisError
from redis.lock import Lock

logger = logging.getLogger(__name__)


class LockUnavailable(RedisError):
    """Redis could not be asked for the lock (unreachable, refused): the work's own code, not
    the lock, says whether that is a skip, a retry or a failure."""


@contextmanager
def lock_held(
    key: str,
    *,
    client: Redis,
    timeout: float,
    wait: float = 0.0,
    renew_every: float | None = None,
) -> Iterator[Lock | None]:
    """Hold the Redis lock `key` for up to `timeout` seconds: yields the lock, or None if
    another holder kept it for `wait` seconds (0: one try). A Redis error while taking it is
    raised as LockUnavailable (a RedisError), for the caller to say what that means for its
    work; one in the block is the block's own.

    With `renew_every`, a thread extends the hold every that many seconds until the block ends.
    `client` is the Redis to lock in (the process's, core.redis_client.get_redis(), for the
    portal's work; the chain client's own for its nonces): this module needs no Django.
    """
    lock = client.lock(
        key,
        timeout=timeout,
        blocking_timeout=wait,
        thread_local=renew_every is None,  # a renewing thread holds the same token
    )
    try:
        acquired = lock.acquire()
    except RedisError as exc:
        raise LockUnavailable(f"cannot take the lock {key} in Redis: {exc}") from exc
    if not acquired:
        yield None
        return
    done = threading.Event()
    renewer = None
    if renew_every is not None:

        def renew() -> None:
            while not done.wait(renew_every):
                with suppress(LockError, RedisError):
                    lock.reacquire()

        renewer = threading.Thread(target=renew, name=f"lock-renew {key}", daemon=True)
        renewer.start()
    try:
        yield lock
    finally:
        done.set()
        if renewer is not None:
            renewer.join()
        with suppress(LockError, RedisError):
            lock.release()


def lock_renew(lock: Lock) -> bool:
    """Extend our hold on `lock` to its full timeout again; False if it expired meanwhile
    (another process may hold it now), for the caller to stop after the step in hand."""
    try:
        lock.reacquire()
    except (LockError, RedisError) as exc:
        logger.warning("lost lock %s (%s)", lock.name, exc)
        return False
    return True
