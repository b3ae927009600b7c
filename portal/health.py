"""Whether this portal process can serve: the parts it needs each answer (GET /readyz).

Four parts, checked at once, each in a thread of its own and given CHECK_TIMEOUT seconds: the
database (a `SELECT 1`), Redis (a PING of the cache's and the broker's), the envelope storage
(its folder exists or can be made, and is writable; or the bucket answers a lookup) and the
chain node (its latest block).
A part that raises or takes longer has failed, and the answer names it and says why, without
the URL or credentials behind it.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from django.conf import settings
from django.db import connections
from redis import Redis

from chainworker.rpc import connect
from core.redis_url import redis_client_for
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)

CHECK_TIMEOUT = 2.0
# A name no envelope has (those are <uuid>.env under folders): looked up, never written.
STORAGE_PROBE = "readyz-probe"


@dataclass(frozen=True)
class PartCheck:
    part: str
    ok: bool
    detail: str  # "ok", or why it failed (no secret: no URL, no credentials)


@lru_cache(maxsize=4)
def redis_probe_client(url: str) -> Redis:
    """A client for the Redis at url whose calls give up after CHECK_TIMEOUT seconds."""
    return redis_client_for(url, socket_connect_timeout=CHECK_TIMEOUT, socket_timeout=CHECK_TIMEOUT)


@lru_cache(maxsize=4)
def chain_probe_client(url: str) -> Any:
    """A Web3 connection to the node at url whose calls give up after CHECK_TIMEOUT seconds."""
    return connect(url, timeout=CHECK_TIMEOUT)


def _database() -> None:
    try:
        with connections["default"].cursor() as cursor:
            cursor.execute("SELECT 1")
    finally:
        connections.close_all()  # this thread's own connection


def _redis() -> None:
    for url in dict.fromkeys([settings.REDIS_URL, settings.BROKER_REDIS_URL]):
        redis_probe_client(url).ping()


def _storage() -> None:
    storage = envelope_storage()
    location = getattr(storage, "location", None)
    if location is not None and not getattr(storage, "bucket_name", None):
        folder = Path(location)
        folder.mkdir(parents=True, exist_ok=True)  # as the first upload would
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PartUnavailable("the envelope folder is not writable")
        return
    storage.exists(STORAGE_PROBE)


def _chain() -> None:
    chain_probe_client(settings.CHAIN_RPC_URL).eth.block_number  # noqa: B018


CHECKS: dict[str, Callable[[], None]] = {
    "database": _database,
    "redis": _redis,
    "storage": _storage,
    "chain": _chain,
}


def readiness() -> list[PartCheck]:
    """Every part checked at once; at most about CHECK_TIMEOUT seconds in all."""
    outcomes: dict[str, str] = {}

    def run(part: str, check: Callable[[], None]) -> None:
        try:
            check()
        except Exception as exc:
            outcomes[part] = _why(part, exc)
        else:
            outcomes[part] = "ok"

    threads = [
        threading.Thread(target=run, args=(part, check), name=f"readyz-{part}", daemon=True)
        for part, check in CHECKS.items()
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(CHECK_TIMEOUT + 0.5)
    return [
        PartCheck(
            part=part,
            ok=outcomes.get(part) == "ok",
            detail=outcomes.get(part, f"no answer within {CHECK_TIMEOUT:g}s"),
        )
        for part in CHECKS
    ]


class PartUnavailable(Exception):
    """A part answered, and the answer says it cannot serve (its message is safe to show)."""


def _why(part: str, exc: Exception) -> str:
    """The failure in a few words for the answer: the exception's class, and the message only
    of our own (a library's may name hosts, ports or credentials); the whole of it is logged."""
    logger.warning("readyz: %s failed: %s: %s", part, exc.__class__.__name__, exc)
    if isinstance(exc, PartUnavailable):
        return str(exc)
    return exc.__class__.__name__
