"""Anchoring: the SM3 digests of pending records go on chain in `dataUploadBatch`
transactions sent by their owner's EOA (ANCHOR_MODE=records), or under Merkle roots sent with
`anchorRoot` (ANCHOR_MODE=root, sharing/services/roots.py), a fair share of one owner per task run.

A record moves pending -> anchored (or failed after ANCHOR_MAX_ATTEMPTS); only these services
and the upload move it. Every run is idempotent: ids are write-once on chain, and a record
found on chain with its digest counts as anchored. Each batch transaction seen on chain is
indexed for the owner's audit page (accounts.models.ChainActivity).
"""

import logging
import time
import uuid
from collections.abc import Callable, Sequence
from contextlib import suppress

from django.conf import settings
from django.db import transaction
from django.db.models import Count, F, Max, Min
from django.utils import timezone
from redis import Redis
from redis.client import Pipeline
from redis.exceptions import RedisError
from redis.lock import Lock

from accounts.models import ChainActivity, ChainState, Owner, Robot
from accounts.selectors import owner_eoa_account
from accounts.services.activity import chain_activity_record
from accounts.services.robot_keys import robot_key_revocations_release
from alerts.services import anchoring_failed_alert
from chainworker.client import AuthROSChain
from chainworker.codec import AnchorItem
from chainworker.errors import (
    ChainUnavailable,
    InsufficientFunds,
    TransactionDropped,
    TransactionReverted,
    TransactionTimeout,
)
from chainworker.services import chain_client, chain_stall_check, chain_work_check
from chainworker.work import CHAIN_TASK, TRANSIENT, ChainWorkNotReady
from core.locks import LockUnavailable, lock_held, lock_renew
from core.outbox import enqueue
from core.redis_client import get_redis, redis_key
from sharing.models import Record, SecurityEvent
from sharing.services.anchor_wait import (
    AWAITING_ROBOT_KEY,
    gas_wait_end,
    gas_wait_start,
    receipt_await,
    records_fail_exhausted,
)
from sharing.services.roots import roots_anchor_round, roots_await_robot_key

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

# How long records on chain but not yet CHAIN_CONFIRMATIONS deep wait before a new look.
ANCHOR_RECHECK_DELAY = 2.0
# Seconds a failed run's flag outlives its longest retry backoff (a busy worker starts late).
RETRY_FLAG_MARGIN = 30


def anchor_schedule(*, owner_id: int, countdown: float | None = None) -> None:
    """Queue a run of `records_anchor` for an owner, unless one is queued already."""
    try:
        first = _anchor_flag_set(get_redis(), owner_id, countdown)
    except RedisError:
        first = True
    _anchor_enqueue(owner_id, first=first, countdown=countdown)


def anchor_after_chain_ready(owner_id: int) -> None:
    """Queue a run for an owner whose registration, or one of whose robots' keys, was just
    confirmed on chain, so that records that waited for it go now
    (accounts.services.registration.owner_chain_ready calls it; sharing/apps.py registers it).
    Past anchor_schedule's flag: a run that found the owner unregistered holds it until its
    retry."""
    enqueue("sharing.tasks.records_anchor", owner_id)


def robot_records_await_anchoring(robot: Robot) -> bool:
    """Whether records the robot's key signed are not anchored yet: its revocation on chain
    waits for them (accounts.services.robot_keys asks; sharing/apps.py registers it)."""
    return Record.objects.filter(
        robot=robot, signer=robot.key_hash, status=Record.Status.PENDING
    ).exists()


def anchor_schedule_queued(pipe: Pipeline, *, owner_id: int) -> Callable[[object], None]:
    """anchor_schedule's round trip queued in `pipe` (to share it with other commands): what
    takes the pipeline's answer to it (raise_on_error=False; a RedisError queues the run)."""
    _anchor_flag_set(pipe, owner_id, None)
    return lambda answer: _anchor_enqueue(
        owner_id, first=isinstance(answer, Exception) or bool(answer), countdown=None
    )


def _anchor_flag_key(owner_id: int) -> str:
    return redis_key("anchor-scheduled", owner_id)


def _anchor_flag_set(client: Redis | Pipeline, owner_id: int, countdown: float | None) -> object:
    """The "a run is queued" flag set unless it is: true when this call set it."""
    flag_ttl = max(30, int(settings.ANCHOR_MAX_WAIT * 4 + (countdown or 0)))
    return client.set(_anchor_flag_key(owner_id), 1, nx=True, ex=flag_ttl)


def _anchor_enqueue(owner_id: int, *, first: bool, countdown: float | None) -> None:
    if first and not enqueue("sharing.tasks.records_anchor", owner_id, countdown=countdown):
        _anchor_unschedule(owner_id)  # not queued: the flag must not keep the sweep from it


def _anchor_flag_hold(owner_id: int) -> None:
    """Keep the "a run is queued" flag set for as long as a retry of the run may take (the
    longest backoff of CHAIN_TASK and a margin): if the retry never runs (its worker died
    with it), the flag lapses and the next upload or the beat sweep queues a run."""
    with suppress(RedisError):
        get_redis().set(
            _anchor_flag_key(owner_id),
            1,
            ex=int(CHAIN_TASK["retry_backoff_max"]) + RETRY_FLAG_MARGIN,
        )


def _anchor_unschedule(owner_id: int) -> None:
    """Drop the "a run is queued" flag of `anchor_schedule`."""
    with suppress(RedisError):
        get_redis().delete(_anchor_flag_key(owner_id))


def records_anchor(*, owner_id: int) -> int:
    """Anchor a fair share of an owner's pending records; return how many were anchored.

    A run sends at most ANCHOR_INFLIGHT dataUploadBatch transactions (consecutive nonces, in
    flight together), waits for their receipts, then hands the worker back and queues the
    next run if records remain, so that owners take turns. A run that finds another worker
    anchoring this owner returns at once: that worker queues the next run when it is done.

    The "a run is queued" flag of `anchor_schedule` stays set while the run works, so uploads
    meanwhile queue nothing (their records are in the next run, which the run queues after
    dropping the flag, or which their own upload queues once it is dropped). A run that fails
    for a transient reason (the node or Redis away, the owner not registered yet) keeps it
    set until its retry: during an outage the uploads wait for that one retrying run instead
    of each queueing a run that retries on its own (a robot's hour of uploads, thousands).

    Records signed by a robot key not on chain yet are left pending (AWAITING_ROBOT_KEY): the
    key's confirmation queues the run that sends them. Once records are anchored, the
    revocations of robot keys that waited for them are queued.

    Idempotent: a record whose id is already on chain with the same digest and owner counts
    as anchored; with another digest it is marked failed and a security event is logged.
    """
    try:
        anchored, sent = _anchor_run(owner_id)
    except TRANSIENT:
        _anchor_flag_hold(owner_id)  # the task retries (CHAIN_TASK): that is the queued run
        raise
    except BaseException:
        _anchor_unschedule(owner_id)
        raise
    _anchor_unschedule(owner_id)
    if anchored:
        robot_key_revocations_release(owner_id=owner_id)
    if sent is not None and _records_left(owner_id):
        # Nothing sent: what is left is on chain awaiting confirmations, so look again after
        # about a block rather than at once.
        anchor_schedule(owner_id=owner_id, countdown=None if sent else ANCHOR_RECHECK_DELAY)
    return anchored


def _records_left(owner_id: int) -> bool:
    """Whether the owner has pending records a next run can send: not those waiting for their
    robot's key, nor (root mode) those behind a tree waiting for one."""
    if settings.ANCHOR_MODE == "root" and roots_await_robot_key(owner_id):
        return False
    pending = Record.objects.filter(owner_id=owner_id, status=Record.Status.PENDING)
    return pending.exclude(AWAITING_ROBOT_KEY).exists()


def _anchor_run(owner_id: int) -> tuple[int, int | None]:
    """One run of `records_anchor`: (records anchored, transactions sent), or None sent when
    it did not run (the owner is gone, or another worker is anchoring them)."""
    owner = Owner.objects.filter(pk=owner_id).first()
    if owner is None:
        logger.warning("records_anchor: owner %s no longer exists", owner_id)
        return 0, None
    if owner.chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"{owner} is not registered on chain yet")
    chain_work_check()  # nothing goes to a reset chain
    # Short, and renewed while waiting for receipts, so a killed worker frees it quickly.
    try:
        with lock_held(
            redis_key("work", f"anchor:{owner_id}"),
            client=get_redis(),
            timeout=settings.ANCHOR_LOCK_TTL,
        ) as lock:
            if lock is None:
                return 0, None
            _wait_for_batch_to_fill(owner_id)
            anchor_round = roots_anchor_round if settings.ANCHOR_MODE == "root" else _anchor_round
            return anchor_round(chain_client(), owner, lock)
    except LockUnavailable as exc:
        raise ChainWorkNotReady(f"cannot lock owner {owner_id} in Redis: {exc}") from exc


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
    """Let records that arrive together share a batch: wait while the owner's uploads keep
    coming (one came in the last ANCHOR_QUIET seconds), until the oldest pending record is
    ANCHOR_MAX_WAIT old, unless a full batch is already waiting. A pause in the uploads
    closes the batch at once: after a robot's batch or a burst the records go on chain
    ANCHOR_QUIET after the last one, not ANCHOR_MAX_WAIT after the first; under a steady
    stream a run still takes what ANCHOR_MAX_WAIT gathered (ANCHOR_QUIET 0: always that)."""
    pending = Record.objects.filter(owner_id=owner_id, status=Record.Status.PENDING).exclude(
        AWAITING_ROBOT_KEY
    )
    full = settings.ANCHOR_ROOT_MAX if settings.ANCHOR_MODE == "root" else settings.ANCHOR_BATCH_MAX
    quiet = settings.ANCHOR_QUIET
    # However the hosts' clocks disagree with the records' times, a run waits at most this.
    deadline = time.monotonic() + settings.ANCHOR_MAX_WAIT
    while True:
        batch = pending.aggregate(
            oldest=Min("created_at"), newest=Max("created_at"), size=Count("pk")
        )
        if batch["oldest"] is None or batch["size"] >= full:
            return
        now = timezone.now()
        waits = [
            settings.ANCHOR_MAX_WAIT - (now - batch["oldest"]).total_seconds(),
            deadline - time.monotonic(),
        ]
        if quiet > 0:
            waits.append(quiet - (now - batch["newest"]).total_seconds())
        wait = min(waits)
        if wait <= 0:
            return
        time.sleep(wait)
        if quiet <= 0:
            return


def _anchor_round(client: AuthROSChain, owner: Owner, lock: Lock) -> tuple[int, int]:
    """One run's sends and receipts; returns (records anchored, transactions sent)."""
    account = owner_eoa_account(owner)
    in_flight: list[tuple[list[Record], str]] = []
    refusal: TransactionReverted | None = None
    cannot_pay: InsufficientFunds | None = None
    for _ in range(settings.ANCHOR_INFLIGHT):
        # "One sender per EOA": stop if our hold on the owner lapsed (a long wait before).
        if not lock_renew(lock):
            break
        sent_ids = [r.pk for batch, _tx in in_flight for r in batch]
        batch = _settle_attempted(client, owner, _next_batch(owner, exclude=sent_ids))
        if not batch:
            break
        batch_ids = [r.pk for r in batch]
        # Counted before sending: a run that dies after the send must look on chain first.
        Record.objects.filter(pk__in=batch_ids).update(anchor_attempts=F("anchor_attempts") + 1)
        try:
            tx_hash = client.data_upload_batch(account, [anchor_item(r) for r in batch], wait=False)
        except ChainUnavailable:
            # The node (or Redis) is away: that is not the records' fault, so it does not
            # count towards ANCHOR_MAX_ATTEMPTS; an outage of any length loses nothing. If the
            # send did reach the node, the next send is refused with RecordExists and settled.
            _attempts_return(batch_ids)
            raise
        except InsufficientFunds as exc:
            # The owner's account cannot pay for gas: an outage that waits, using up no attempt,
            # with its reason shown; the operator tops the account up and the task (or the
            # sweep) sends again.
            _attempts_return(batch_ids)
            pending = Record.objects.filter(owner_id=owner.pk, status=Record.Status.PENDING)
            gas_wait_start(owner.pk, pending.exclude(pk__in=sent_ids))
            cannot_pay = exc
            break
        except TransactionReverted as exc:
            if exc.error_name != "RecordExists":
                refusal = exc
                break
            # Someone anchored some of these already: settle them all from the chain; the
            # rest go in the next run.
            _settle_attempted(client, owner, batch, force=True)
            break
        if not in_flight:
            gas_wait_end(owner.pk)
        in_flight.append((batch, tx_hash))
    anchored = 0
    for position, (batch, tx_hash) in enumerate(in_flight):
        try:
            receipt = receipt_await(client, tx_hash, lock)
        except TransactionTimeout:
            # Waited the whole receipt timeout: if the chain made no block meanwhile it is
            # stalled, which is not these records' fault, so (as for ChainUnavailable) the
            # attempts go back; chain_stall_check pauses every sender and tells the operator.
            if chain_stall_check(since=time.time() - client.receipt_timeout).stalled:
                unmined = [r.pk for waiting, _tx in in_flight[position:] for r in waiting]
                _attempts_return(unmined)
            raise
        except TransactionDropped:
            # The node lost it (restarted without it, or lost its latest blocks): not the
            # records' fault either; the next run sends them again.
            _attempts_return([r.pk for waiting, _tx in in_flight[position:] for r in waiting])
            raise
        block = int(receipt["blockNumber"])
        Record.objects.filter(pk__in=[r.pk for r in batch], status=Record.Status.PENDING).update(
            status=Record.Status.ANCHORED,
            tx_hash=tx_hash,
            block_number=block,
            anchored_at=timezone.now(),
        )
        chain_activity_record(
            owner=owner,
            kind=ChainActivity.Kind.ANCHORED,
            tx_hash=tx_hash,
            block_number=block,
            record_count=len(batch),
        )
        anchored += len(batch)
    if refusal is not None:
        raise refusal
    if cannot_pay is not None:
        raise cannot_pay
    return anchored, len(in_flight)


def _attempts_return(record_ids: list[uuid.UUID]) -> None:
    Record.objects.filter(
        pk__in=record_ids, status=Record.Status.PENDING, anchor_attempts__gt=0
    ).update(anchor_attempts=F("anchor_attempts") - 1)


def _next_batch(owner: Owner, *, exclude: list[uuid.UUID]) -> list[Record]:
    pending = Record.objects.filter(owner_id=owner.pk, status=Record.Status.PENDING).exclude(
        AWAITING_ROBOT_KEY
    )
    records_fail_exhausted(owner, pending)
    pending = pending.exclude(pk__in=exclude)
    return list(pending.order_by("created_at", "seq")[: settings.ANCHOR_BATCH_MAX])


def anchor_item(record: Record) -> AnchorItem:
    return AnchorItem(
        record_id=record.id,
        digest=bytes.fromhex(record.digest),
        time=record.captured_at,
        data_type=record.data_type,
    )


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
        on_chain = client.data_query(record.id, owner=owner.eoa_address)
        if on_chain is None:
            still_pending.append(record)
        elif on_chain.digest.hex() == record.digest and (
            on_chain.owner.lower() == owner.eoa_address.lower()
        ):
            event = client.upload_event(record.id, owner=owner.eoa_address)
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
            if event is not None:
                # Found after the run that sent it died: its batch is counted from what we hold.
                chain_activity_record(
                    owner=owner,
                    kind=ChainActivity.Kind.ANCHORED,
                    tx_hash=event.tx_hash,
                    block_number=event.block_number,
                    record_count=Record.objects.filter(owner=owner, tx_hash=event.tx_hash).count(),
                )
        else:
            _chain_digest_mismatch(record, on_chain.digest.hex(), on_chain.owner)
    return still_pending


def record_chain_mismatch(*, record: Record, chain_digest: str, chain_owner: str) -> None:
    """The chain holds another digest or owner under the record's id: the record is failed and
    a SecurityEvent raised (found by anchoring or by the reconciliation)."""
    _chain_digest_mismatch(record, chain_digest, chain_owner)


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
    anchoring_failed_alert(
        owner=record.owner,
        record_ids=[record.pk],
        reason="the chain holds another digest or owner for this record id",
        once=True,  # found again by each reconciliation that looks: told once
    )
    security_log.error(
        "record %s: chain holds digest %s (owner %s), we stored %s",
        record.pk,
        chain_digest,
        chain_owner,
        record.digest,
    )
