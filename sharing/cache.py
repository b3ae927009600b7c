"""The Redis cache of envelopes. Durable storage holds the copy that counts; a Redis that is
down, flushed or full only makes reads slower."""

import logging
import uuid

from django.conf import settings
from redis.exceptions import RedisError

from portal.redis_client import get_redis, redis_key
from sharing.models import Record
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)


def _key(record_id: uuid.UUID | str) -> str:
    return redis_key("envelope", record_id)


def envelope_cache_put(record_id: uuid.UUID | str, data: bytes) -> None:
    if len(data) > settings.ENVELOPE_CACHE_MAX_ITEM_BYTES:
        return
    try:
        get_redis().set(_key(record_id), data, ex=settings.ENVELOPE_CACHE_TTL)
    except RedisError as exc:
        logger.warning("envelope cache unavailable (put %s): %s", record_id, exc)


def envelope_cache_get(record_id: uuid.UUID | str) -> bytes | None:
    try:
        return get_redis().get(_key(record_id))
    except RedisError as exc:
        logger.warning("envelope cache unavailable (get %s): %s", record_id, exc)
        return None


def envelope_cache_evict(record_id: uuid.UUID | str) -> None:
    try:
        get_redis().delete(_key(record_id))
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
