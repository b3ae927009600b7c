"""The Redis cache of envelopes. Durable storage holds the copy that counts; a Redis that is
down, flushed or full only makes reads slower.

Bounded two ways: each entry lives ENVELOPE_CACHE_TTL seconds, and all entries together hold
at most ENVELOPE_CACHE_MAX_BYTES; past that the oldest entries are evicted first. The bound is
kept by the cache itself (a Lua script, atomic across every web and worker process), not by
Redis's maxmemory, because the same Redis holds the Celery queues, nonces and locks, which
must never be evicted. Beside each entry `<prefix>:envelope:<id>`:

    <prefix>:envelope-index   sorted set: record id -> time it was cached (ms)
    <prefix>:envelope-sizes   hash: record id -> bytes
    <prefix>:envelope-bytes   the total of those sizes
"""

import logging
import time
import uuid
from collections.abc import Sequence
from functools import lru_cache

import redis
from django.conf import settings
from redis.commands.core import Script
from redis.exceptions import RedisError

from core.redis_client import get_redis, redis_key
from sharing.models import Record
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)


def _key(record_id: uuid.UUID | str) -> str:
    return redis_key("envelope", record_id)


# KEYS: index, sizes, total. ARGV: entry key prefix, now (ms), ttl (s), max bytes, then
# for a put: id, data; for an evict: id only.
_FORGET = """
local function forget(id)
  redis.call('DEL', ARGV[1] .. id)
  local size = tonumber(redis.call('HGET', KEYS[2], id) or '0')
  redis.call('HDEL', KEYS[2], id)
  redis.call('ZREM', KEYS[1], id)
  if size > 0 then redis.call('DECRBY', KEYS[3], size) end
end
"""
_PUT = (
    _FORGET
    + """
local now, ttl, max = tonumber(ARGV[2]), tonumber(ARGV[3]), tonumber(ARGV[4])
local id, data = ARGV[5], ARGV[6]
local expired = redis.call('ZRANGEBYSCORE', KEYS[1], '-inf', now - ttl * 1000, 'LIMIT', 0, 1000)
for _, old in ipairs(expired) do
  forget(old)
end
forget(id)
redis.call('SET', ARGV[1] .. id, data, 'EX', ttl)
redis.call('ZADD', KEYS[1], now, id)
redis.call('HSET', KEYS[2], id, #data)
local total = redis.call('INCRBY', KEYS[3], #data)
local evicted = 0
while total > max do
  local oldest = redis.call('ZRANGE', KEYS[1], 0, 0)[1]
  if oldest == nil or oldest == id then break end
  forget(oldest)
  evicted = evicted + 1
  total = tonumber(redis.call('GET', KEYS[3]) or '0')
end
return evicted
"""
)
_EVICT = _FORGET + "forget(ARGV[5])\nreturn 0\n"


def _bookkeeping() -> list[str]:
    return [
        redis_key("envelope-index"),
        redis_key("envelope-sizes"),
        redis_key("envelope-bytes"),
    ]


@lru_cache(maxsize=8)
def _script(client: redis.Redis, source: str) -> Script:
    """The script registered once per client (it hashes its source for EVALSHA)."""
    return client.register_script(source)


def _run(script: str, *args: object, now_ms: int | None = None) -> int:
    now = int(time.time() * 1000) if now_ms is None else now_ms
    return _script(get_redis(), script)(keys=_bookkeeping(), args=[*_fixed_args(now), *args])


def _fixed_args(now_ms: int) -> list[object]:
    """The arguments every script call starts with: entry key prefix, now, ttl, max bytes."""
    return [
        redis_key("envelope", ""),
        now_ms,
        settings.ENVELOPE_CACHE_TTL,
        settings.ENVELOPE_CACHE_MAX_BYTES,
    ]


def envelope_cache_put(
    record_id: uuid.UUID | str, data: bytes, *, now_ms: int | None = None
) -> None:
    envelope_cache_put_many([(record_id, data)], now_ms=now_ms)


def envelope_cache_put_many(
    items: Sequence[tuple[uuid.UUID | str, bytes]], *, now_ms: int | None = None
) -> None:
    """Cache each (record id, data), in one round trip to Redis; one too big is not cached."""
    limit = min(settings.ENVELOPE_CACHE_MAX_ITEM_BYTES, settings.ENVELOPE_CACHE_MAX_BYTES)
    items = [(record_id, data) for record_id, data in items if len(data) <= limit]
    if not items:
        return
    now = int(time.time() * 1000) if now_ms is None else now_ms
    try:
        client = get_redis()
        script = _script(client, _PUT)
        with client.pipeline(transaction=False) as pipe:
            for record_id, data in items:
                args = [*_fixed_args(now), str(record_id), data]
                script(keys=_bookkeeping(), args=args, client=pipe)
            evicted = sum(int(n or 0) for n in pipe.execute())
    except RedisError as exc:
        logger.warning("envelope cache unavailable (put %d envelopes): %s", len(items), exc)
        return
    if evicted:
        logger.debug("envelope cache full: evicted the %d oldest entries", evicted)


def envelope_cache_bytes() -> int:
    """What the cached envelopes hold together, by the cache's own count."""
    try:
        return int(get_redis().get(redis_key("envelope-bytes")) or 0)
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
        _run(_EVICT, str(record_id))
    except RedisError as exc:
        logger.warning("envelope cache unavailable (evict %s): %s", record_id, exc)


def envelope_fetch(record: Record) -> tuple[bytes, str]:
    """The record's envelope and where it came from ("cache" or "storage")."""
    cached = envelope_cache_get(record.id)
    if cached is not None:
        return cached, "cache"
    with envelope_storage().open(record.storage_name, "rb") as handle:
        data = handle.read()
    envelope_cache_put(record.id, data)
    return data, "storage"
