"""Nonces for locally signed transactions, safe across processes and hosts.

One sender per EOA at a time: a Redis lock is held while a nonce is chosen, the transaction
signed and handed to the node; it is renewed before every send, and a send whose lock expired
meanwhile does not happen. The next nonce is the larger of the Redis counter (covers
nodes behind a load balancer whose pending count lags) and the node's pending count (covers
transactions sent by anyone else). A counter ahead of the node for longer than any plausible
lag means transactions were dropped (a node restarted without its mempool): the node wins.
After a nonce error the counter is resynced from the node.
"""

import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import redis
from redis.exceptions import LockError, RedisError
from redis.lock import Lock

from core.locks import LockUnavailable, lock_held

logger = logging.getLogger(__name__)


class NonceLockTimeout(RuntimeError):
    """Another process held the sender's lock for longer than we were willing to wait."""


class NonceLockLost(NonceLockTimeout):
    """Our hold on the sender's lock expired before we sent: another process may be using
    the nonce, so nothing may be sent with it."""


class NonceStoreUnavailable(RuntimeError):
    """Redis cannot be reached, so no transaction may be sent (nonces would collide)."""


@dataclass
class NonceReservation:
    """A nonce handed out under the sender's lock; `commit` once the node accepted it."""

    address: str
    nonce: int
    _manager: "RedisNonceManager"
    _fetch_from_node: Callable[[str], int]
    _lock: Lock

    def hold(self) -> None:
        """Renew the sender's lock for another full timeout; call before each send.

        Raises NonceLockLost when it expired meanwhile (a slow node): the nonce may be taken.
        """
        try:
            self._lock.reacquire()
        except LockError as exc:
            raise NonceLockLost(f"lost the nonce lock of {self.address}: {exc}") from exc
        except RedisError as exc:
            raise NonceStoreUnavailable(f"cannot renew the nonce lock in Redis: {exc}") from exc

    def commit(self) -> None:
        self._manager._store(self.address, self.nonce + 1)

    def resync(self) -> int:
        """Forget the counter and take the node's pending count (after a nonce error)."""
        self.nonce = self._fetch_from_node(self.address)
        self._manager._store(self.address, self.nonce)
        return self.nonce


class RedisNonceManager:
    """Hands out nonces per (chain, address) under a Redis lock."""

    def __init__(
        self,
        client: redis.Redis,
        *,
        namespace: str,
        prefix: str = "authros",
        lock_timeout: float = 60.0,
        blocking_timeout: float = 120.0,
        counter_ttl: int = 24 * 3600,
        stale_after: float = 30.0,
    ) -> None:
        self._redis = client
        self._namespace = namespace
        self._prefix = prefix
        self._lock_timeout = lock_timeout
        self._blocking_timeout = blocking_timeout
        self._counter_ttl = counter_ttl
        self._stale_after = stale_after

    def _key(self, address: str) -> str:
        return f"{self._prefix}:nonce:{self._namespace}:{address.lower()}"

    def _store(self, address: str, value: int) -> None:
        try:
            self._redis.set(self._key(address), f"{value}:{time.time()}", ex=self._counter_ttl)
        except RedisError as exc:
            raise NonceStoreUnavailable(f"cannot store nonce in Redis: {exc}") from exc

    @contextmanager
    def reserve(
        self, address: str, fetch_from_node: Callable[[str], int]
    ) -> Iterator[NonceReservation]:
        """Hold the sender's lock and yield the next nonce to use."""
        try:
            with lock_held(
                self._key(address) + ":lock",
                timeout=self._lock_timeout,
                wait=self._blocking_timeout,
                client=self._redis,
            ) as lock:
                if lock is None:
                    raise NonceLockTimeout(
                        f"sender {address} stayed locked for {self._blocking_timeout}s"
                    )
                try:
                    stored = self._redis.get(self._key(address))
                except RedisError as exc:
                    raise NonceStoreUnavailable(f"cannot read nonce from Redis: {exc}") from exc
                nonce = self._choose(address, stored, fetch_from_node(address))
                yield NonceReservation(address, nonce, self, fetch_from_node, lock)
        except LockUnavailable as exc:  # taking the lock (the block takes none of its own)
            raise NonceStoreUnavailable(f"cannot lock nonce in Redis: {exc}") from exc

    def _choose(self, address: str, stored: bytes | None, from_node: int) -> int:
        if stored is None:
            return from_node
        counter, written_at = (float(part) for part in stored.decode().split(":"))
        if counter > from_node and time.time() - written_at > self._stale_after:
            logger.warning(
                "nonce counter %d for %s is ahead of the node (%d): transactions were dropped",
                int(counter),
                address,
                from_node,
            )
            return from_node
        return max(int(counter), from_node)

    def forget(self, address: str) -> None:
        """Drop the counter so the next reservation starts from the node's pending count."""
        try:
            self._redis.delete(self._key(address))
        except RedisError as exc:
            raise NonceStoreUnavailable(f"cannot reset nonce in Redis: {exc}") from exc
