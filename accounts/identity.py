"""The identity check (the paper's, against DESIGN.md's commitment): the key commitment on
chain for an owner is the one of the key the portal holds.

It runs when a registration or a rotation is confirmed (accounts.services.registration),
before uploads (sharing.services) and before every view, in the worker (sharing.verification).
The chain's answer is kept in Redis per owner and block, so a burst of requests costs one chain
read.
"""

import logging
import time
from collections.abc import Sequence
from contextlib import suppress

from django.conf import settings
from django.db import transaction
from redis.exceptions import RedisError

from accounts.errors import IdentityMismatch
from accounts.events import account_event_record
from accounts.models import AccountEvent, ChainState, Owner, OwnerKey
from accounts.selectors import owner_keys
from chainworker.client import AuthROSChain
from chainworker.errors import ChainError
from chainworker.services import chain_client
from core.redis_client import get_redis, redis_key

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")
# Seconds the chain's commitment for an owner at one block stays in Redis when
# IDENTITY_BLOCK_CACHE_SECONDS is 0 (checked per block: blocks move on).
IDENTITY_CACHE_TTL = 300
# What the contract answers for an EOA that has no commitment on it.
NOT_REGISTERED = "0x" + "00" * 32


def owner_identity_check(
    *, owner: Owner, fresh: bool = False, keys: Sequence[OwnerKey] | None = None
) -> bool:
    """The identity check: the key commitment on chain for `owner` is the one of the key the
    portal holds (the newest confirmed one; while a rotation is on its way, the new one too).

    True when it was checked and holds; False when it cannot be checked (the owner is not on
    chain yet, or not on this chain any more: a reset or lost blocks, which reconciliation
    repairs; no contract; the chain does not answer), which is accepted. Otherwise raises
    IdentityMismatch, after an AccountEvent (one per commitment seen on chain) and a line on
    the "authros.security" log. The chain's answer is kept in Redis per owner and block, so
    checks in a burst of requests cost no chain call; `fresh` asks the chain itself (to read
    back what a confirmed transaction wrote). `keys`, the owner's keys newest first, saves
    reading them again where the caller has them.
    """
    expected = _identity_expected(owner, keys)
    if not expected:
        return False
    try:
        client = chain_client()
        on_chain = _commitment_on_chain(client, owner, fresh=fresh)
        if on_chain not in expected and not fresh:
            # The cached block may predate a rotation just confirmed: ask the chain itself.
            on_chain = _commitment_on_chain(client, owner, fresh=True)
    except ChainError as exc:
        logger.warning("the identity of %s was not checked: %s", owner, exc)
        return False
    if on_chain in expected:
        return True
    if on_chain == NOT_REGISTERED:
        # Nobody's key: the chain lost the registration. Not another key, so not refused.
        logger.warning("%s is not registered on the live chain; reconciliation repairs it", owner)
        return False
    _identity_mismatch_record(owner, on_chain=on_chain, expected=expected[0])
    raise IdentityMismatch(
        f"the key commitment on chain for {owner} differs from the key the portal holds; "
        "uploads and views are refused until an operator looks"
    )


def _identity_expected(owner: Owner, keys: Sequence[OwnerKey] | None = None) -> list[str]:
    """The commitments that may be on chain for the owner, the newest confirmed key's first;
    none while the owner is not on chain."""
    if owner.chain_state != ChainState.CONFIRMED:
        return []
    if keys is None:
        keys = owner_keys(owner)
    newer_pending: list[str] = []
    for key in keys:
        if key.chain_state == ChainState.CONFIRMED:
            return [key.commitment.lower(), *newer_pending]
        if key.chain_state == ChainState.PENDING:
            newer_pending.append(key.commitment.lower())
    return []


def _commitment_on_chain(client: AuthROSChain, owner: Owner, *, fresh: bool) -> str:
    """The owner's commitment on chain; unless `fresh`, as some process read it at most
    IDENTITY_BLOCK_CACHE_SECONDS ago (as fresh as the chain head every process shares: this
    process keeps that answer until its Redis entry expires), or, with that set to 0, at the
    latest block."""
    key = redis_key("identity", client.chain_key, client.address, owner.eoa_address)
    seconds = settings.IDENTITY_BLOCK_CACHE_SECONDS
    block = client.latest_block() if fresh or seconds <= 0 else None
    if not fresh:
        if block is None:
            known = _known.get(key)
            if known is not None and known[0] > time.monotonic():
                return known[1]
        value, expires_in = _cache_get(key)
        seen_at, _, commitment = value.partition(" ")
        if commitment and (block is None or seen_at == str(block)):
            if block is None:
                _know(key, commitment, expires_in)
            return commitment
    on_chain = "0x" + client.commitment_of(owner.eoa_address).hex()
    _cache_set(
        key,
        f"{'-' if block is None else block} {on_chain}",
        seconds=seconds if seconds > 0 else IDENTITY_CACHE_TTL,
    )
    if seconds > 0:
        _know(key, on_chain, seconds)
    return on_chain


# What this process read from Redis (or the chain) under IDENTITY_BLOCK_CACHE_SECONDS, until
# the Redis entry it came from expires: as fresh as every other process's answer, without a
# round trip per request. Per block (the setting at 0) every request still asks Redis.
_known: dict[str, tuple[float, str]] = {}
_KNOWN_MAX = 10_000


def _know(key: str, commitment: str, seconds: float) -> None:
    if len(_known) >= _KNOWN_MAX:
        _known.clear()
    _known[key] = (time.monotonic() + seconds, commitment)


def _cache_get(key: str) -> tuple[str, float]:
    """The cached value and the seconds it has left ("" and 0 when there is none)."""
    try:
        with get_redis().pipeline(transaction=False) as pipe:
            value, left_ms = pipe.get(key).pttl(key).execute()
    except RedisError:
        return "", 0.0  # without Redis every check asks the chain
    if value is None:
        return "", 0.0
    return value.decode(), max(0, left_ms) / 1000


def _cache_set(key: str, value: str, *, seconds: float) -> None:
    with suppress(RedisError):
        get_redis().set(key, value, px=max(1, int(seconds * 1000)))


def _identity_mismatch_record(owner: Owner, *, on_chain: str, expected: str) -> None:
    """One AccountEvent and one log line per commitment seen on chain, not one per request."""
    with transaction.atomic():
        # Checks running side by side for the owner write one event between them.
        Owner.objects.select_for_update().filter(pk=owner.pk).first()
        seen = AccountEvent.objects.filter(
            owner=owner,
            kind=AccountEvent.Kind.IDENTITY_MISMATCH,
            detail__chain_commitment=on_chain,
        ).exists()
        if seen:
            return
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.IDENTITY_MISMATCH,
            detail={"chain_commitment": on_chain, "expected_commitment": expected},
        )
    security_log.error(
        "identity check failed for %s (EOA %s): the key commitment on chain is %s, the key "
        "the portal holds commits to %s; uploads and views are refused",
        owner,
        owner.eoa_address,
        on_chain,
        expected,
    )
