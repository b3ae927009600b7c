"""The Redis connection shared by the portal's own code (locks, nonces, caches)."""

from functools import lru_cache

import redis
from django.conf import settings


@lru_cache(maxsize=4)
def _client_for(url: str) -> redis.Redis:
    return redis.Redis.from_url(url, socket_timeout=5, socket_connect_timeout=5)


def get_redis() -> redis.Redis:
    return _client_for(settings.REDIS_URL)


def redis_key(*parts: object) -> str:
    """A key in the portal's namespace: `<REDIS_KEY_PREFIX>:part:part...`."""
    return ":".join([settings.REDIS_KEY_PREFIX, *map(str, parts)])
