"""Actions on the chain that the portal takes: deploying, building the client, status."""

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from datetime import timedelta

from django.conf import settings
from django.db import transaction
from django.db.models import F
from django.utils import timezone
from eth_account import Account
from eth_account.signers.local import LocalAccount
from redis.exceptions import LockError, RedisError
from redis.lock import Lock
from web3.types import TxReceipt

from accounts.models import ChainState, Owner, OwnerKey
from accounts.selectors import owner_eoa_account
from chainworker.chain import (
    AnchorItem,
    AuthROSChain,
    ChainUnavailable,
    ContractNotDeployed,
    TransactionReverted,
    TransactionTimeout,
    TxResult,
)
from chainworker.models import Deployment
from chainworker.outbox import enqueue
from chainworker.selectors import deployment_active
from portal.redis_client import get_redis, redis_key
from portal.secrets import load_or_create_secret
from sharing.models import Grant, Record, SecurityEvent

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

# The operator pays for deployment and funds new EOAs; keep it topped up on dev chains.
DEV_OPERATOR_FLOAT_WEI = 10_000 * 10**18

# How long records on chain but not yet CHAIN_CONFIRMATIONS deep wait before a new look.
ANCHOR_RECHECK_DELAY = 2.0

_clients: dict[str, AuthROSChain] = {}
_clients_lock = threading.Lock()


def operator_account() -> LocalAccount:
    """The operator (contract admin) account: from CHAIN_OPERATOR_KEY, else a 0600 file."""
    key = settings.CHAIN_OPERATOR_KEY
    if key:
        return Account.from_key(key)
    secret = load_or_create_secret(settings.SECRETS_DIR / "operator.key", nbytes=32)
    return Account.from_key(secret)


def chain_client() -> AuthROSChain:
    """The process's client for the configured chain, pointed at the active deployment."""
    url = settings.CHAIN_RPC_URL
    with _clients_lock:
        client = _clients.get(url)
        if client is None:
            client = AuthROSChain(
                url,
                redis_client=get_redis(),
                receipt_timeout=settings.CHAIN_RECEIPT_TIMEOUT,
                rpc_timeout=settings.CHAIN_RPC_TIMEOUT,
                confirmations=settings.CHAIN_CONFIRMATIONS,
                redis_prefix=settings.REDIS_KEY_PREFIX,
                nonce_lock_timeout=settings.CHAIN_NONCE_LOCK_TIMEOUT,
            )
            _clients[url] = client
    address = settings.CHAIN_CONTRACT_ADDRESS or _recorded_address(client)
    if address and address != client._address:
        client.use_contract(address)
    return client


def _recorded_address(client: AuthROSChain) -> str | None:
    deployment = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
    return deployment.address if deployment else None


def operator_ensure_funded(*, client: AuthROSChain, operator: LocalAccount) -> None:
    """On a development chain, top up the operator; on a real one, only warn."""
    if client.balance(operator.address) >= DEV_OPERATOR_FLOAT_WEI // 10:
        return
    if settings.CHAIN_DEV_FAUCET and client.dev_faucet(operator.address, DEV_OPERATOR_FLOAT_WEI):
        return
    logger.warning(
        "operator %s has a low balance on chain %s: fund it (genesis alloc on a PoA network)",
        operator.address,
        client.chain_id,
    )


@dataclass(frozen=True)
class DeployOutcome:
    deployment: Deployment
    created: bool
    reason: str


def contract_deploy(*, force: bool = False) -> DeployOutcome:
    """Deploy the AuthROS contract once per chain and record where it is.

    Idempotent: with an active deployment whose code is still on chain, nothing is sent.
    `force` deploys a new contract and retires the old record.
    """
    client = chain_client()
    operator = operator_account()
    with _exclusive(f"deploy:{client.chain_key}", timeout=300, wait=300):
        current = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
        if current and not force:
            if client.has_code(current.address):
                client.use_contract(current.address)
                return DeployOutcome(current, created=False, reason="already deployed")
            reason = f"no code at recorded address {current.address} (chain was reset)"
        else:
            reason = "forced" if current else "first deployment"
        operator_ensure_funded(client=client, operator=operator)
        result = client.deploy(operator)
        with transaction.atomic():
            if current:
                Deployment.objects.filter(pk=current.pk).update(is_active=False)
            deployment = Deployment.objects.create(
                chain_id=client.chain_id,
                genesis_hash=client.genesis_hash,
                address=client.address,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                deployer=operator.address,
                compiler_version=client.artifact.compiler_version,
                source_keccak=client.artifact.source_keccak,
                rpc_url=settings.CHAIN_RPC_URL if not client.is_in_process else "",
            )
    logger.info(
        "deployed AuthROS at %s on chain %s (%s)", deployment.address, client.chain_id, reason
    )
    return DeployOutcome(deployment, created=True, reason=reason)


def chain_status() -> dict[str, object]:
    """What an operator wants to know about the chain; raises ChainUnavailable if it is down."""
    client = chain_client()
    operator = operator_account()
    status: dict[str, object] = {
        "node_url": settings.CHAIN_RPC_URL,
        "client_version": client.client_version,
        "chain_id": client.chain_id,
        "latest_block": client.latest_block(),
        "contract_address": None,
        "admin": None,
        "operator": operator.address,
        "operator_balance_wei": client.balance(operator.address),
        "confirmations": settings.CHAIN_CONFIRMATIONS,
    }
    try:
        status["contract_address"] = client.address
        status["admin"] = client.admin()
        status["record_count"] = client.record_count()
    except ContractNotDeployed:
        status["problem"] = "contract not deployed: run `manage.py chain_deploy`"
    return status


# --- chain work for owners, keys, grants and records -------------------------------------


class ChainWorkNotReady(Exception):
    """What this work depends on is not on chain yet (e.g. the owner is not registered)."""


@contextmanager
def _exclusive(name: str, *, timeout: float = 60.0, wait: float = 30.0) -> Iterator[Lock]:
    """A Redis lock so only one worker does this piece of chain work at a time."""
    lock = get_redis().lock(redis_key("work", name), timeout=timeout, blocking_timeout=wait)
    if not lock.acquire():
        raise ChainWorkNotReady(f"{name} is being worked on by another worker")
    try:
        yield lock
    finally:
        with suppress(LockError, RedisError):
            lock.release()


def owner_register_on_chain(*, owner_id: int) -> Owner:
    """Fund the owner's EOA, enroll it (operator) and register its key commitment."""
    with _exclusive(f"owner:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT * 3 + 30):
        owner = Owner.objects.select_related("user").get(pk=owner_id)
        if owner.chain_state == ChainState.CONFIRMED:
            return owner
        client = chain_client()
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        first_key = owner.keys.order_by("created_at").first()
        # Each step is written as soon as it is on chain, so progress pages move step by step.
        step = Owner.objects.filter(pk=owner.pk).update
        funding = settings.CHAIN_EOA_FUNDING_WEI
        if client.balance(owner.eoa_address) < funding // 2:
            step(fund_tx=client.transfer(operator, owner.eoa_address, funding).tx_hash)
        if not client.is_enrolled(owner.eoa_address):
            step(enroll_tx=client.enroll(operator, owner.eoa_address).tx_hash)
        if not client.is_registered(owner.eoa_address):
            commitment = bytes.fromhex(first_key.commitment.removeprefix("0x"))
            result = client.register(owner_eoa_account(owner), commitment)
            step(register_tx=result.tx_hash, registered_block=result.block_number)
            OwnerKey.objects.filter(pk=first_key.pk).update(
                chain_state=ChainState.CONFIRMED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
            )
        else:
            OwnerKey.objects.filter(pk=first_key.pk).update(chain_state=ChainState.CONFIRMED)
        step(chain_state=ChainState.CONFIRMED, chain_error="")
        owner.refresh_from_db()
    # Keys rotated (and records uploaded) while registration was pending can go now.
    for key in owner.keys.filter(chain_state=ChainState.PENDING):
        enqueue("chainworker.tasks.key_rotate", key.pk)
    anchor_schedule(owner_id=owner.pk)
    return owner


def key_rotate_on_chain(*, owner_key_id: int) -> OwnerKey:
    """Put a rotated key's commitment on chain (`rotateKey`), in the order keys were made."""
    key = OwnerKey.objects.select_related("owner").get(pk=owner_key_id)
    owner = key.owner
    if key.chain_state == ChainState.CONFIRMED:
        return key
    if owner.chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"{owner} is not registered on chain yet")
    if owner.keys.filter(created_at__lt=key.created_at, chain_state=ChainState.PENDING).exists():
        raise ChainWorkNotReady(f"an older key of {owner} is not on chain yet")
    with _exclusive(f"owner:{owner.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        client = chain_client()
        commitment = bytes.fromhex(key.commitment.removeprefix("0x"))
        fields: dict[str, object] = {"chain_state": ChainState.CONFIRMED}
        if client.commitment_of(owner.eoa_address) != commitment:
            result = client.rotate_key(owner_eoa_account(owner), commitment)
            fields.update(tx_hash=result.tx_hash, block_number=result.block_number)
        OwnerKey.objects.filter(pk=key.pk).update(**fields)
    key.refresh_from_db()
    return key


def grant_sync_on_chain(*, grant_id: int) -> Grant:
    """Make the chain agree with the portal's grant: authorityGrant or authorityRevoke."""
    grant = Grant.objects.select_related("owner", "grantee").get(pk=grant_id)
    for party in (grant.owner, grant.grantee):
        if party.chain_state != ChainState.CONFIRMED:
            raise ChainWorkNotReady(f"{party} is not registered on chain yet")
    pair = f"grant:{grant.owner_id}:{grant.grantee_id}"
    with _exclusive(pair, timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        grant.refresh_from_db()
        try:
            _grant_sync(grant)
        except TransactionReverted as exc:
            if grant.status != Grant.Status.PENDING:
                raise  # a revocation is never given up: it fails loudly and the sweep retries
            # The contract will refuse this grant every time: say so, do not retry forever.
            Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(
                status=Grant.Status.FAILED, failure_reason=str(exc)[:300]
            )
            logger.error("grant %s refused on chain: %s", grant.pk, exc)
    grant.refresh_from_db()
    return grant


def _grant_sync(grant: Grant) -> None:
    client = chain_client()
    owner, grantee = grant.owner, grant.grantee
    has_access = client.has_access(owner.eoa_address, grantee.eoa_address)
    if grant.status == Grant.Status.PENDING:
        fields: dict[str, object] = {"status": Grant.Status.ACTIVE}
        if not has_access:
            result = _tolerating(
                "AlreadyGranted",
                lambda: client.authority_grant(owner_eoa_account(owner), grantee.eoa_address),
            )
            if result is not None:
                fields.update(grant_tx=result.tx_hash, grant_block=result.block_number)
        Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(**fields)
    elif grant.status == Grant.Status.REVOKING:
        fields = {"status": Grant.Status.REVOKED}
        if has_access:
            result = _tolerating(
                "NoGrant",
                lambda: client.authority_revoke(owner_eoa_account(owner), grantee.eoa_address),
            )
            if result is not None:
                fields.update(revoke_tx=result.tx_hash, revoke_block=result.block_number)
        Grant.objects.filter(pk=grant.pk, status=Grant.Status.REVOKING).update(**fields)


def _tolerating(error_name: str, send: Callable[[], TxResult]) -> TxResult | None:
    """Send; a refusal meaning "already the case" (a lost race) counts as done."""
    try:
        return send()
    except TransactionReverted as exc:
        if exc.error_name == error_name:
            return None
        raise


def anchor_schedule(*, owner_id: int, countdown: float | None = None) -> None:
    """Queue a run of `records_anchor` for an owner, unless one is queued already."""
    flag_ttl = max(30, int(settings.ANCHOR_MAX_WAIT * 4 + (countdown or 0)))
    try:
        first = get_redis().set(redis_key("anchor-scheduled", owner_id), 1, nx=True, ex=flag_ttl)
    except RedisError:
        first = True
    if first and not enqueue("chainworker.tasks.records_anchor", owner_id, countdown=countdown):
        _anchor_unschedule(owner_id)  # not queued: the flag must not keep the sweep from it


def _anchor_unschedule(owner_id: int) -> None:
    """Drop the "a run is queued" flag of `anchor_schedule`."""
    with suppress(RedisError):
        get_redis().delete(redis_key("anchor-scheduled", owner_id))


def records_anchor(*, owner_id: int) -> int:
    """Anchor a fair share of an owner's pending records; return how many were anchored.

    A run sends at most ANCHOR_INFLIGHT dataUploadBatch transactions (consecutive nonces, in
    flight together), waits for their receipts, then hands the worker back and queues the
    next run if records remain, so that owners take turns. A run that finds another worker
    anchoring this owner returns at once: that worker queues the next run when it is done.

    Idempotent: a record whose id is already on chain with the same digest and owner counts
    as anchored; with another digest it is marked failed and a security event is logged.
    """
    _anchor_unschedule(owner_id)
    owner = Owner.objects.filter(pk=owner_id).first()
    if owner is None:
        logger.warning("records_anchor: owner %s no longer exists", owner_id)
        return 0
    if owner.chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"{owner} is not registered on chain yet")
    # Short, and renewed while waiting for receipts, so a killed worker frees it quickly.
    lock = get_redis().lock(
        redis_key("work", f"anchor:{owner_id}"), timeout=settings.ANCHOR_LOCK_TTL
    )
    try:
        if not lock.acquire(blocking=False):
            return 0
    except RedisError as exc:
        raise ChainWorkNotReady(f"cannot lock owner {owner_id} in Redis: {exc}") from exc
    try:
        _wait_for_batch_to_fill(owner_id)
        anchored, sent = _anchor_round(chain_client(), owner, lock)
    finally:
        with suppress(LockError, RedisError):
            lock.release()
    if Record.objects.filter(owner_id=owner_id, status=Record.Status.PENDING).exists():
        # Nothing sent: what is left is on chain awaiting confirmations, so look again after
        # about a block rather than at once.
        anchor_schedule(owner_id=owner_id, countdown=None if sent else ANCHOR_RECHECK_DELAY)
    return anchored


def records_reanchor(*, record_ids: Sequence[uuid.UUID]) -> int:
    """Put failed records back in the queue (an operator's repair); how many were failed."""
    with transaction.atomic():
        failed = Record.objects.filter(pk__in=record_ids, status=Record.Status.FAILED)
        owner_ids = sorted(set(failed.values_list("owner_id", flat=True)))
        count = failed.update(status=Record.Status.PENDING, anchor_attempts=0, failure_reason="")
        for owner_id in owner_ids:
            transaction.on_commit(lambda o=owner_id: anchor_schedule(owner_id=o))
    return count


def _wait_for_batch_to_fill(owner_id: int) -> None:
    """Let records that arrive together share a batch: wait until the oldest pending record
    is ANCHOR_MAX_WAIT old, unless a full batch is already waiting."""
    pending = Record.objects.filter(owner_id=owner_id, status=Record.Status.PENDING)
    oldest = pending.order_by("created_at").values_list("created_at", flat=True).first()
    if oldest is None or pending.count() >= settings.ANCHOR_BATCH_MAX:
        return
    remaining = settings.ANCHOR_MAX_WAIT - (timezone.now() - oldest).total_seconds()
    if remaining > 0:
        time.sleep(min(remaining, settings.ANCHOR_MAX_WAIT))


def _anchor_round(client: AuthROSChain, owner: Owner, lock: Lock) -> tuple[int, int]:
    """One run's sends and receipts; returns (records anchored, transactions sent)."""
    account = owner_eoa_account(owner)
    in_flight: list[tuple[list[Record], str]] = []
    refusal: TransactionReverted | None = None
    for _ in range(settings.ANCHOR_INFLIGHT):
        # "One sender per EOA": stop if our hold on the owner lapsed (a long wait before).
        if not _renew(lock):
            break
        sent_ids = [r.pk for batch, _tx in in_flight for r in batch]
        batch = _settle_attempted(client, owner, _next_batch(owner.pk, exclude=sent_ids))
        if not batch:
            break
        batch_ids = [r.pk for r in batch]
        # Counted before sending: a run that dies after the send must look on chain first.
        Record.objects.filter(pk__in=batch_ids).update(anchor_attempts=F("anchor_attempts") + 1)
        try:
            tx_hash = client.data_upload_batch(
                account, [_anchor_item(r) for r in batch], wait=False
            )
        except ChainUnavailable:
            # The node (or Redis) is away: that is not the records' fault, so it does not
            # count towards ANCHOR_MAX_ATTEMPTS; an outage of any length loses nothing. If the
            # send did reach the node, the next send is refused with RecordExists and settled.
            Record.objects.filter(pk__in=batch_ids, anchor_attempts__gt=0).update(
                anchor_attempts=F("anchor_attempts") - 1
            )
            raise
        except TransactionReverted as exc:
            if exc.error_name != "RecordExists":
                refusal = exc
                break
            # Someone anchored some of these already: settle them all from the chain; the
            # rest go in the next run.
            _settle_attempted(client, owner, batch, force=True)
            break
        in_flight.append((batch, tx_hash))
    anchored = 0
    for batch, tx_hash in in_flight:
        receipt = _await_receipt(client, tx_hash, lock)
        Record.objects.filter(pk__in=[r.pk for r in batch], status=Record.Status.PENDING).update(
            status=Record.Status.ANCHORED,
            tx_hash=tx_hash,
            block_number=int(receipt["blockNumber"]),
            anchored_at=timezone.now(),
        )
        anchored += len(batch)
    if refusal is not None:
        raise refusal
    return anchored, len(in_flight)


def _renew(lock: Lock) -> bool:
    """Extend our hold on a lock; False if it expired meanwhile (another worker may own it).

    Losing it is safe, not fatal: ids are write-once on chain and a duplicate send is
    settled as already anchored. We stop after the batch in hand.
    """
    try:
        lock.reacquire()
    except (LockError, RedisError) as exc:
        logger.warning("lost lock %s (%s); finishing the batch in hand", lock.name, exc)
        return False
    return True


def _next_batch(owner_id: int, *, exclude: list[uuid.UUID]) -> list[Record]:
    pending = Record.objects.filter(owner_id=owner_id, status=Record.Status.PENDING)
    exhausted = pending.filter(anchor_attempts__gte=settings.ANCHOR_MAX_ATTEMPTS)
    exhausted.update(
        status=Record.Status.FAILED,
        failure_reason=f"not anchored after {settings.ANCHOR_MAX_ATTEMPTS} attempts",
    )
    pending = pending.exclude(pk__in=exclude)
    return list(pending.order_by("created_at", "seq")[: settings.ANCHOR_BATCH_MAX])


def _anchor_item(record: Record) -> AnchorItem:
    return AnchorItem(
        record_id=record.id,
        digest=bytes.fromhex(record.digest),
        time=record.captured_at,
        data_type=record.data_type,
    )


def _await_receipt(client: AuthROSChain, tx_hash: str, lock: Lock) -> TxReceipt:
    """Wait for the receipt in short steps, keeping the owner's anchoring lock alive."""
    deadline = time.monotonic() + client.receipt_timeout
    while True:
        step = min(settings.ANCHOR_LOCK_TTL / 3, max(deadline - time.monotonic(), 0.1))
        try:
            return client.wait_for_receipt(tx_hash, timeout=step)
        except TransactionTimeout:
            if time.monotonic() >= deadline:
                raise
            _renew(lock)


def _settle_attempted(
    client: AuthROSChain, owner: Owner, batch: list[Record], *, force: bool = False
) -> list[Record]:
    """Look up records a previous attempt may have anchored; return those still to send."""
    still_pending = []
    latest = None
    for record in batch:
        if record.anchor_attempts == 0 and not force:
            still_pending.append(record)
            continue
        on_chain = client.data_query(record.id)
        if on_chain is None:
            still_pending.append(record)
        elif on_chain.digest.hex() == record.digest and (
            on_chain.owner.lower() == owner.eoa_address.lower()
        ):
            event = client.upload_event(record.id)
            if client.confirmations:
                latest = client.latest_block() if latest is None else latest
                if event is None or latest - event.block_number < client.confirmations:
                    continue  # on chain, not deep enough yet: neither anchored nor resent
            Record.objects.filter(pk=record.pk, status=Record.Status.PENDING).update(
                status=Record.Status.ANCHORED,
                tx_hash=event.tx_hash if event else "",
                block_number=event.block_number if event else None,
                anchored_at=timezone.now(),
            )
        else:
            _chain_digest_mismatch(record, on_chain.digest.hex(), on_chain.owner)
    return still_pending


def _chain_digest_mismatch(record: Record, chain_digest: str, chain_owner: str) -> None:
    Record.objects.filter(pk=record.pk).update(
        status=Record.Status.FAILED,
        failure_reason="the chain holds another digest or owner for this record id",
    )
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.CHAIN_DIGEST_MISMATCH,
        record=record,
        owner=record.owner,
        detail={"stored": record.digest, "chain": chain_digest, "chain_owner": chain_owner},
    )
    security_log.error(
        "record %s: chain holds digest %s (owner %s), we stored %s",
        record.pk,
        chain_digest,
        chain_owner,
        record.digest,
    )


def sweep_stale() -> dict[str, int]:
    """Queue again all chain work pending for longer than ANCHOR_STALE_AFTER."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    owners = set(
        Record.objects.filter(status=Record.Status.PENDING, created_at__lt=cutoff).values_list(
            "owner_id", flat=True
        )
    )
    for owner_id in owners:
        anchor_schedule(owner_id=owner_id)
    registrations = list(
        Owner.objects.filter(chain_state=ChainState.PENDING, created_at__lt=cutoff).values_list(
            "pk", flat=True
        )
    )
    for owner_id in registrations:
        enqueue("chainworker.tasks.owner_register", owner_id)
    keys = list(
        OwnerKey.objects.filter(
            chain_state=ChainState.PENDING,
            created_at__lt=cutoff,
            owner__chain_state=ChainState.CONFIRMED,
        ).values_list("pk", flat=True)
    )
    for key_pk in keys:
        enqueue("chainworker.tasks.key_rotate", key_pk)
    grants = list(
        Grant.objects.filter(
            status__in=[Grant.Status.PENDING, Grant.Status.REVOKING], updated_at__lt=cutoff
        ).values_list("pk", flat=True)
    )
    for grant_pk in grants:
        enqueue("chainworker.tasks.grant_sync", grant_pk)
    return {
        "anchor_owners": len(owners),
        "registrations": len(registrations),
        "keys": len(keys),
        "grants": len(grants),
    }
