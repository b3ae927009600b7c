"""The envelope cache's bounds: a TTL per entry and a total size, oldest evicted first; and
an upload's cache and anchoring flag set in one round trip, whatever state Redis is in."""

import uuid

import pytest
import redis

from core.redis_client import get_redis, redis_key
from sharing.cache import (
    _key,
    envelope_cache_bytes,
    envelope_cache_evict,
    envelope_cache_get,
    envelope_cache_put,
)
from sharing.models import Record
from sharing.services import anchoring
from sharing.services.uploads import record_create_batch

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


@pytest.mark.django_db
def test_an_upload_caches_and_queues_its_anchoring_in_one_round_trip(
    make_robot, monkeypatch, django_capture_on_commit_callbacks
):
    """After the commit: the envelopes cached and the owner's anchoring flagged and queued,
    one round trip to Redis for both."""
    setup = make_robot()
    queued = []
    monkeypatch.setattr(anchoring, "enqueue", lambda *args, **kwargs: queued.append(args) or True)
    sent = []
    real_send = redis.connection.AbstractConnection.send_packed_command
    monkeypatch.setattr(
        redis.connection.AbstractConnection,
        "send_packed_command",
        lambda self, *a, **k: sent.append(a) or real_send(self, *a, **k),
    )
    with django_capture_on_commit_callbacks() as after_commit:
        records = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1), setup.seal(2)])
    sent.clear()
    for callback in after_commit:
        callback()
    assert len(sent) == 1
    assert [envelope_cache_get(record.id) is not None for record in records] == [True, True]
    assert queued == [("sharing.tasks.records_anchor", setup.owner.pk)]
    assert get_redis().exists(redis_key("anchor-scheduled", setup.owner.pk))

    # The flag set: the next upload queues no second run.
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(3)])
    assert len(queued) == 1


@pytest.mark.django_db
def test_an_upload_after_redis_forgot_its_scripts_is_still_cached(
    make_robot, django_capture_on_commit_callbacks
):
    setup = make_robot()
    get_redis().script_flush()
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1)])[0]
    assert envelope_cache_get(record.id) is not None


@pytest.mark.django_db
def test_an_upload_while_redis_is_unreachable_is_stored_and_its_anchoring_queued(
    make_robot, monkeypatch, django_capture_on_commit_callbacks
):
    """The cache is skipped and the run queued anyway (the flag cannot say one is queued)."""
    setup = make_robot()
    queued = []
    monkeypatch.setattr(anchoring, "enqueue", lambda *args, **kwargs: queued.append(args) or True)

    def unreachable(self, *args, **kwargs):
        raise redis.ConnectionError("Redis is down")

    monkeypatch.setattr(redis.client.Pipeline, "execute", unreachable)
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1)])[0]
    monkeypatch.undo()
    assert Record.objects.filter(pk=record.pk).exists()
    assert envelope_cache_get(record.id) is None
    assert queued == [("sharing.tasks.records_anchor", setup.owner.pk)]
