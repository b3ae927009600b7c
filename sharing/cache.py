"""The Redis cache of envelopes. Durable storage holds the copy that counts; a Redis that is
down, flushed or full only makes reads slower.

Bounded two ways: each entry lives ENVELOPE_CACHE_TTL seconds, and all entries together hold
at most ENVELOPE_CACHE_MAX_BYTES; past that the oldest entries are evicted first. The bound is
kept by the cache itself (a Lua script, atomic across every web and worker process), not by
Redis's maxmemory, because the same Redis holds the Celery queues, nonces and locks, which
must never be evicted. Beside each entry `<prefix>:{envelope}:<id>`:

    <prefix>:{envelope}-index   sorted set: record id -> time it was cached (ms)
    <prefix>:{envelope}-sizes   hash: record id -> bytes
    <prefix>:{envelope}-bytes   the total of those sizes

All in one hash slot (the {envelope} tag), and every script names the keys it touches, so
the cache runs on a Redis Cluster as on one Redis.
"""

import hashlib
import logging
import time
import uuid
from collections.abc import Callable, Sequence
from contextlib import suppress
from functools import lru_cache

import redis
from django.conf import settings
from redis.commands.core import Script
from redis.exceptions import NoScriptError, RedisError

from core.redis_client import get_redis, redis_key
from sharing.models import Record
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)


# Every key of the cache carries the hash tag {envelope}: in a Redis Cluster they share one
# slot, so a script may touch several of them; and every script names the keys it touches.
_TAG = "{envelope}"


def _key(record_id: uuid.UUID | str) -> str:
    return redis_key(_TAG, record_id)


# KEYS: index, sizes, total, then the entry key of each record put or evicted. ARGV: now
# (ms), ttl (s), max bytes, then each record's id (and for a put its data). `drop` takes an id
# out of the bookkeeping. The entry keys of others dropped (expired, or evicted past the
# total) are not named, so the script leaves them: an expired one is gone by its own TTL, and
# a put returns the ids it evicted, whose keys the caller deletes.
_DROP = """
local function drop(id)
  local size = tonumber(redis.call('HGET', KEYS[2], id) or '0')
  redis.call('HDEL', KEYS[2], id)
  redis.call('ZREM', KEYS[1], id)
  if size > 0 then redis.call('DECRBY', KEYS[3], size) end
end
"""
_PUT = (
    _DROP
    + """
local now, ttl, max = tonumber(ARGV[1]), tonumber(ARGV[2]), tonumber(ARGV[3])
local expired = redis.call('ZRANGEBYSCORE', KEYS[1], '-inf', now - ttl * 1000, 'LIMIT', 0, 1000)
for _, old in ipairs(expired) do
  drop(old)
end
local fresh = {}
for i = 4, #KEYS do
  local id, data = ARGV[2 * i - 4], ARGV[2 * i - 3]
  drop(id)
  redis.call('SET', KEYS[i], data, 'EX', ttl)
  redis.call('ZADD', KEYS[1], now, id)
  redis.call('HSET', KEYS[2], id, #data)
  redis.call('INCRBY', KEYS[3], #data)
  fresh[id] = true
end
local total = tonumber(redis.call('GET', KEYS[3]) or '0')
local evicted = {}
local skip = 0
while total > max do
  -- The oldest entry, past those just put (which may share its millisecond).
  local oldest = redis.call('ZRANGE', KEYS[1], skip, skip)[1]
  if oldest == nil then break end
  if fresh[oldest] then
    skip = skip + 1
  else
    drop(oldest)
    evicted[#evicted + 1] = oldest
    total = tonumber(redis.call('GET', KEYS[3]) or '0')
  end
end
return evicted
"""
)
_EVICT = _DROP + "drop(ARGV[4])\nredis.call('DEL', KEYS[4])\nreturn 0\n"
# What EVALSHA names _PUT by, as redis-py's Script computes it.
_PUT_SHA = hashlib.sha1(_PUT.encode(), usedforsecurity=False).hexdigest()


def _keys(*record_ids: uuid.UUID | str) -> list[str]:
    """What a script for `record_ids` touches: the bookkeeping, then their entries."""
    return [
        redis_key(f"{_TAG}-index"),
        redis_key(f"{_TAG}-sizes"),
        redis_key(f"{_TAG}-bytes"),
        *map(_key, record_ids),
    ]


@lru_cache(maxsize=8)
def _script(client: redis.Redis, source: str) -> Script:
    """The script registered once per client (it hashes its source for EVALSHA)."""
    return client.register_script(source)


def _args(now_ms: int, *more: object) -> list[object]:
    return [now_ms, settings.ENVELOPE_CACHE_TTL, settings.ENVELOPE_CACHE_MAX_BYTES, *more]


def envelope_cache_put(
    record_id: uuid.UUID | str, data: bytes, *, now_ms: int | None = None
) -> None:
    envelope_cache_put_many([(record_id, data)], now_ms=now_ms)


def envelope_cache_put_many(
    items: Sequence[tuple[uuid.UUID | str, bytes]], *, now_ms: int | None = None
) -> None:
    """Cache each (record id, data), in one round trip to Redis (one script for them all);
    one too big is not cached."""
    items = _cacheable(items)
    if not items:
        return
    try:
        client = get_redis()
        keys, args = _put_call(items, now_ms)
        _evicted_drop(client, _script(client, _PUT)(keys=keys, args=args))
    except RedisError as exc:
        logger.warning("envelope cache unavailable (put %d envelopes): %s", len(items), exc)


def envelope_cache_put_queued(
    pipe: redis.client.Pipeline, items: Sequence[tuple[uuid.UUID | str, bytes]]
) -> Callable[[object], None] | None:
    """envelope_cache_put_many queued in `pipe`, to share its round trip with other commands:
    what takes the pipeline's answer to it (raise_on_error=False: a RedisError is logged, a
    script Redis no longer holds is loaded and run again), or None when nothing was queued."""
    items = _cacheable(items)
    if not items:
        return None
    keys, args = _put_call(items, None)
    pipe.evalsha(_PUT_SHA, len(keys), *keys, *args)

    def finish(answer: object) -> None:
        if isinstance(answer, NoScriptError):
            envelope_cache_put_many(items)  # Redis restarted: loads the script
        elif isinstance(answer, Exception):
            logger.warning("envelope cache unavailable (put %d envelopes): %s", len(items), answer)
        else:
            with suppress(RedisError):
                _evicted_drop(get_redis(), answer)

    return finish


def _cacheable(
    items: Sequence[tuple[uuid.UUID | str, bytes]],
) -> list[tuple[uuid.UUID | str, bytes]]:
    limit = min(settings.ENVELOPE_CACHE_MAX_ITEM_BYTES, settings.ENVELOPE_CACHE_MAX_BYTES)
    return [(record_id, data) for record_id, data in items if len(data) <= limit]


def _put_call(
    items: Sequence[tuple[uuid.UUID | str, bytes]], now_ms: int | None
) -> tuple[list[str], list[object]]:
    now = int(time.time() * 1000) if now_ms is None else now_ms
    ids = [str(record_id) for record_id, _ in items]
    args = _args(now, *(part for record_id, data in items for part in (str(record_id), data)))
    return _keys(*ids), args


def _evicted_drop(client: redis.Redis, evicted: Sequence[bytes]) -> None:
    """The entries a put evicted: out of the bookkeeping already, their keys go now (a second
    round trip only when the cache is full)."""
    if evicted:
        client.delete(*(_key(old.decode()) for old in evicted))
        logger.debug("envelope cache full: evicted the %d oldest entries", len(evicted))


def envelope_cache_bytes() -> int:
    """What the cached envelopes hold together, by the cache's own count."""
    try:
        return int(get_redis().get(redis_key(f"{_TAG}-bytes")) or 0)
    except RedisError:
        return 0


def envelope_cache_get(record_id: uuid.UUID | str) -> bytes | None:
    try:
        return get_redis().get(_key(record_id))
    except RedisError as exc:
        logger.warning("envelope cache unavailable (get %s): %s", record_id, exc)
        return None


def envelope_cache_evict(record_id: uuid.UUID | str) -> None:
    try:
        now = int(time.time() * 1000)
        _script(get_redis(), _EVICT)(keys=_keys(record_id), args=_args(now, str(record_id)))
    except RedisError as exc:
        logger.warning("envelope cache unavailable (evict %s): %s", record_id, exc)


def envelope_fetch(record: Record) -> tuple[bytes, str]:
    """The record's envelope and where it came from ("cache" or "storage")."""
    (fetched,) = envelopes_fetch([record])
    if isinstance(fetched, FileNotFoundError):
        raise fetched
    return fetched


def envelopes_fetch(
    records: Sequence[Record],
) -> list[tuple[bytes, str] | FileNotFoundError]:
    """Each record's envelope and where it came from ("cache" or "storage"), or the
    FileNotFoundError of one whose durable copy is gone: the cached ones in one round trip to
    Redis (MGET), the others read from storage and cached in one more."""
    cached: list[bytes | None] = [None] * len(records)
    if records:
        try:
            cached = get_redis().mget([_key(record.id) for record in records])
        except RedisError as exc:
            logger.warning("envelope cache unavailable (get %d): %s", len(records), exc)
    fetched: list[tuple[bytes, str] | FileNotFoundError] = []
    stored: list[tuple[uuid.UUID, bytes]] = []
    storage = envelope_storage()
    for record, data in zip(records, cached, strict=True):
        if data is not None:
            fetched.append((data, "cache"))
            continue
        try:
            with storage.open(record.storage_name, "rb") as handle:
                data = handle.read()
        except FileNotFoundError as exc:
            fetched.append(exc)
            continue
        fetched.append((data, "storage"))
        stored.append((record.id, data))
    envelope_cache_put_many(stored)
    return fetched
