"""The one Redis lock helper (core/locks.py), against the real Redis: one holder at a time, a
wait bounded by `wait`, a hold renewed by its holder or by a thread, released whatever the
block does, and Redis gone said as LockUnavailable."""

import time

import pytest
from redis.exceptions import ConnectionError as RedisConnectionError

from core.locks import LockUnavailable, lock_held, lock_renew
from core.redis_client import get_redis, redis_key

pytestmark = pytest.mark.nodb


def test_one_holder_at_a_time_and_released_after_the_block(redis_client):
    key = redis_key("test", "lock", "one")
    with lock_held(key, client=get_redis(), timeout=10) as first:
        assert first is not None
        with lock_held(key, client=get_redis(), timeout=10) as second:
            assert second is None  # held elsewhere: one try, no wait
    assert not redis_client.exists(key)
    with lock_held(key, client=get_redis(), timeout=10) as again:
        assert again is not None


def test_released_when_the_block_raises(redis_client):
    key = redis_key("test", "lock", "raises")
    with (
        pytest.raises(ValueError, match="the work failed"),
        lock_held(key, client=get_redis(), timeout=10),
    ):
        raise ValueError("the work failed")
    assert not redis_client.exists(key)


def test_a_waiting_taker_gives_up_after_wait(redis_client):
    key = redis_key("test", "lock", "wait")
    with lock_held(key, client=get_redis(), timeout=10):
        started = time.monotonic()
        with lock_held(key, client=get_redis(), timeout=10, wait=0.3) as waited:
            assert waited is None
        assert 0.15 <= time.monotonic() - started < 5  # tries every 0.1 s until the wait is up


def test_renewed_by_its_holder_and_by_a_thread(redis_client):
    key = redis_key("test", "lock", "renew")
    with lock_held(key, client=get_redis(), timeout=1) as lock:
        redis_client.pexpire(key, 100)
        assert lock_renew(lock)
        assert redis_client.pttl(key) > 500
    with lock_held(key, client=get_redis(), timeout=1, renew_every=0.2):
        time.sleep(1.5)  # past the timeout: only the thread kept it
        assert redis_client.exists(key)
    assert not redis_client.exists(key)


def test_a_lost_hold_is_no_error(redis_client):
    key = redis_key("test", "lock", "lost")
    with lock_held(key, client=get_redis(), timeout=10) as lock:
        redis_client.delete(key)  # expired meanwhile
        assert not lock_renew(lock)
    # Released without an error, and free for the next holder.
    with lock_held(key, client=get_redis(), timeout=10) as again:
        assert again is not None


def test_redis_gone_is_lock_unavailable():
    class Down:
        def lock(self, *args, **kwargs):
            return DownLock()

    class DownLock:
        def acquire(self):
            raise RedisConnectionError("Redis is down")

    with pytest.raises(LockUnavailable), lock_held("any", client=Down(), timeout=1):
        pytest.fail("the block runs only under the lock")
