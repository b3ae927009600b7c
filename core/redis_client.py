"""The Redis connection shared by the portal's own code (locks, nonces, caches), and Django's
cache on it.

REDIS_URL may name a plain Redis, Redis behind Sentinels or a Redis Cluster (core/redis_url.py).
"""

from functools import lru_cache

import redis
from django.conf import settings
from django.core.cache.backends.redis import RedisCache, RedisCacheClient
from redis.cluster import RedisCluster

from core.redis_url import redis_client_for


@lru_cache(maxsize=4)
def redis_client(url: str) -> redis.Redis | RedisCluster:
    """One client (and connection pool) per URL for the whole process."""
    return redis_client_for(url)


def get_redis() -> redis.Redis | RedisCluster:
    return redis_client(settings.REDIS_URL)


def redis_key(*parts: object) -> str:
    """A key in the portal's namespace: `<REDIS_KEY_PREFIX>:part:part...`."""
    return ":".join([settings.REDIS_KEY_PREFIX, *map(str, parts)])


class _SharedClientCache(RedisCacheClient):
    """Django's Redis cache client on the portal's client for the URL (any REDIS_URL form)."""

    def get_client(self, key: object = None, *, write: bool = False) -> redis.Redis | RedisCluster:
        return redis_client(self._servers[0])

    # MGET and MSET are one slot's: on a Cluster the keys are read and written one by one.
    def get_many(self, keys: list[str]) -> dict[str, object]:
        client = self.get_client()
        if not isinstance(client, RedisCluster):
            return super().get_many(keys)
        values = client.mget_nonatomic(keys)
        return {
            key: self._serializer.loads(value)
            for key, value in zip(keys, values, strict=True)
            if value is not None
        }

    def set_many(self, data: dict[str, object], timeout: int | None) -> None:
        client = self.get_client(write=True)
        if not isinstance(client, RedisCluster):
            return super().set_many(data, timeout)
        if timeout == 0:  # Django's "expire at once"
            return self.delete_many(list(data))
        with client.pipeline() as pipe:
            for key, value in data.items():
                pipe.set(key, self._serializer.dumps(value), ex=timeout)
            pipe.execute()
        return None


class SharedRedisCache(RedisCache):
    """Django's cache (CACHES) on the Redis of REDIS_URL, through the portal's own client:
    Django's own backend reads only plain redis:// URLs and splits LOCATION at commas."""

    def __init__(self, server: str, params: dict) -> None:
        super().__init__(server, params)
        self._servers = [server]
        self._class = _SharedClientCache
