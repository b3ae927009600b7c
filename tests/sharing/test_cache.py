"""The envelope cache's bounds: a TTL per entry and a total size, oldest evicted first."""

import uuid

import pytest

from core.redis_client import get_redis
from sharing.cache import (
    _key,
    envelope_cache_bytes,
    envelope_cache_evict,
    envelope_cache_get,
    envelope_cache_put,
)

NOW = 1_800_000_000_000  # ms


@pytest.fixture
def small_cache(settings):
    settings.ENVELOPE_CACHE_MAX_BYTES = 3000
    settings.ENVELOPE_CACHE_TTL = 60
    return settings


def _ids(count: int) -> list[str]:
    return [str(uuid.uuid4()) for _ in range(count)]


def test_past_the_total_bound_the_oldest_entries_go_first(small_cache):
    ids = _ids(5)
    for offset, record_id in enumerate(ids):
        envelope_cache_put(record_id, bytes([offset]) * 1000, now_ms=NOW + offset)
    assert [envelope_cache_get(record_id) is not None for record_id in ids] == [
        False,
        False,
        True,
        True,
        True,
    ]
    assert envelope_cache_bytes() == 3000
    assert envelope_cache_get(ids[4]) == b"\x04" * 1000


def test_caching_the_same_record_again_is_counted_once(small_cache):
    record_id = _ids(1)[0]
    for attempt in range(4):
        envelope_cache_put(record_id, b"x" * 800, now_ms=NOW + attempt)
    assert envelope_cache_bytes() == 800


def test_entries_past_their_ttl_no_longer_count(small_cache):
    first, second = _ids(2)
    envelope_cache_put(first, b"a" * 2000, now_ms=NOW)
    # 61 s later the first entry's TTL has run out: it neither counts nor pushes anything out.
    envelope_cache_put(second, b"b" * 2000, now_ms=NOW + 61_000)
    assert envelope_cache_bytes() == 2000
    assert envelope_cache_get(second) == b"b" * 2000


def test_evicting_releases_the_entry_and_its_bytes(small_cache):
    record_id = _ids(1)[0]
    envelope_cache_put(record_id, b"z" * 1000)
    envelope_cache_evict(record_id)
    assert envelope_cache_get(record_id) is None
    assert envelope_cache_bytes() == 0


def test_entries_carry_the_ttl(small_cache):
    record_id = _ids(1)[0]
    envelope_cache_put(record_id, b"t" * 10)
    assert 0 < get_redis().ttl(_key(record_id)) <= 60


def test_an_envelope_larger_than_an_item_may_be_is_not_cached(small_cache):
    small_cache.ENVELOPE_CACHE_MAX_ITEM_BYTES = 100
    record_id = _ids(1)[0]
    envelope_cache_put(record_id, b"y" * 101)
    assert envelope_cache_get(record_id) is None
    assert envelope_cache_bytes() == 0


def test_entries_cached_in_the_same_millisecond_are_still_evicted_oldest_first(small_cache):
    """The newest entry may sort before older ones of its millisecond: it is passed over, not
    a reason to stop evicting."""
    ids = sorted(_ids(4), reverse=True)  # the last one put sorts first among equal times
    for record_id in ids:
        envelope_cache_put(record_id, b"s" * 1000, now_ms=NOW)
    assert envelope_cache_bytes() == 3000
    assert envelope_cache_get(ids[-1]) == b"s" * 1000
