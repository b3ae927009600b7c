"""The portal's Redis scripts on a real Redis Cluster (three masters, redis-server from
Debian): every script names the keys it touches, and the keys of one script share a slot
(hash tags), which a cluster requires and redis-py's cluster client checks."""

import time
import uuid
from collections.abc import Iterator

import pytest
import redis

from accounts import signup_limits
from sharing import cache
from stack.redis_cluster import RedisCluster, start_redis_cluster


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[RedisCluster]:
    with start_redis_cluster(tmp_path_factory.mktemp("redis-cluster")) as started:
        yield started


@pytest.fixture
def on_cluster(cluster, monkeypatch, settings) -> redis.RedisCluster:
    client = cluster.client()
    settings.REDIS_KEY_PREFIX = f"authros-cluster-{uuid.uuid4().hex[:8]}"
    monkeypatch.setattr(cache, "get_redis", lambda: client)
    monkeypatch.setattr(signup_limits, "get_redis", lambda: client)
    return client


def test_the_envelope_cache_keeps_its_bounds_on_a_cluster(on_cluster, settings):
    settings.ENVELOPE_CACHE_MAX_BYTES = 3000
    settings.ENVELOPE_CACHE_TTL = 60
    ids = [str(uuid.uuid4()) for _ in range(5)]
    now = int(time.time() * 1000)  # each entry a millisecond later: "oldest" is well defined
    for offset, record_id in enumerate(ids):
        cache.envelope_cache_put(record_id, bytes([offset]) * 1000, now_ms=now + offset)
    assert [cache.envelope_cache_get(record_id) for record_id in ids] == [
        None,
        None,
        b"\x02" * 1000,
        b"\x03" * 1000,
        b"\x04" * 1000,
    ]
    assert cache.envelope_cache_bytes() == 3000
    cache.envelope_cache_evict(ids[4])
    assert cache.envelope_cache_get(ids[4]) is None
    assert cache.envelope_cache_bytes() == 2000
    # The entries are spread over the cluster's nodes no more than the bookkeeping: one slot.
    slots = {on_cluster.keyslot(key) for key in cache._keys(ids[2])}
    assert len(slots) == 1


def test_a_batch_is_cached_in_one_pipeline_on_a_cluster(on_cluster, settings):
    settings.ENVELOPE_CACHE_MAX_BYTES = 10_000
    items = [(str(uuid.uuid4()), b"e" * 100) for _ in range(20)]
    cache.envelope_cache_put_many(items)
    assert all(cache.envelope_cache_get(record_id) == data for record_id, data in items)
    assert cache.envelope_cache_bytes() == 2000


def test_the_signup_limits_hold_on_a_cluster(on_cluster, settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "2/hour"
    settings.SIGNUP_RATE_TOTAL = "100/hour"
    taken = [signup_limits.signup_slot_take(address="10.0.0.7") for _ in range(3)]
    assert [slot.allowed for slot in taken] == [True, True, False]
    assert taken[2].retry_after > 0
    signup_limits.signup_slot_give_back(taken[1])
    assert signup_limits.signup_slot_take(address="10.0.0.7").allowed
