"""Owners' identity on chain, run by the worker: registration (fund, enroll, register the
first key's commitment) and key rotations, in the order the keys were made.

The tasks in accounts/tasks.py call these; chain_work_sweep queues again what waits too long
(robots' keys of robot_keys.py too), and owners_reconcile and owners_chain_reset (run by
sharing.services.reconcile) put back what the chain lost, robots' keys included (robot_keys.py
reads those back). Once an owner is
registered, or one of its robots' keys is, the work that waited for it in the apps above
accounts (sharing's anchoring) is started through the listeners they register here, so that
accounts imports none of them.
"""

import logging
import uuid
from collections.abc import Callable, Sequence
from datetime import timedelta

from django.conf import settings
from django.db import transaction
from django.db.models import QuerySet
from django.utils import timezone

from accounts.errors import IdentityMismatch
from accounts.identity import owner_identity_check
from accounts.models import Approval, ChainActivity, ChainState, Owner, OwnerKey, Robot
from accounts.selectors import owner_eoa_account
from accounts.services.activity import chain_activity_record
from accounts.services.funding import eoa_fund, eoa_funding_amount, gas_sweep
from chainworker.client import AuthROSChain
from chainworker.errors import InsufficientFunds
from chainworker.services import (
    chain_client,
    chain_work_check,
    operator_account,
    operator_ensure_funded,
)
from chainworker.work import ChainWorkNotReady, exclusive
from core.outbox import enqueue

logger = logging.getLogger(__name__)

# Told the id of an owner once something its chain work waited for is confirmed on chain: its
# registration (owner_register_on_chain) or one of its robots' keys (robot_keys.py).
OwnerChainReadyListener = Callable[[int], None]

_chain_ready_listeners: list[OwnerChainReadyListener] = []


def owner_chain_ready_listener_register(listener: OwnerChainReadyListener) -> None:
    """Have `listener(owner_id)` called once an owner's registration, or one of its robots'
    keys, is confirmed on chain: an app above accounts registers it when Django starts (its
    AppConfig.ready), as apps do with chainworker/backlog.py, to start the work that waited."""
    if listener not in _chain_ready_listeners:
        _chain_ready_listeners.append(listener)


def owner_chain_ready(owner_id: int) -> None:
    """Tell the registered listeners that work waiting for the owner on chain may go now."""
    for listener in _chain_ready_listeners:
        listener(owner_id)


def owner_register_on_chain(*, owner_id: int) -> Owner:
    """Fund the owner's EOA, enroll it (operator) and register its key commitment."""
    with exclusive(f"owner:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT * 3 + 30):
        owner = Owner.objects.select_related("user").get(pk=owner_id)
        if owner.chain_state == ChainState.CONFIRMED or owner.approval != Approval.APPROVED:
            return owner
        chain_work_check()  # nothing goes to a reset chain
        client = chain_client()
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        first_key = owner.keys.order_by("created_at").first()
        # Each step is written as soon as it is on chain, so progress pages move step by step.
        step = Owner.objects.filter(pk=owner.pk).update
        funding = eoa_funding_amount(fee_per_gas=client.fee_per_gas())
        if funding and client.balance(owner.eoa_address) < funding // 2:
            fund_tx = eoa_fund(owner=owner, client=client, operator=operator, amount_wei=funding)
            if fund_tx is None:
                owner.refresh_from_db()
                return owner  # over the funding budget: it waits; chain_work_sweep retries it
            step(fund_tx=fund_tx)
            chain_activity_record(owner=owner, kind=ChainActivity.Kind.FUNDED, tx_hash=fund_tx)
        if not client.is_enrolled(owner.eoa_address):
            enrolled = client.enroll(operator, owner.eoa_address)
            step(enroll_tx=enrolled.tx_hash)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.ENROLLED,
                tx_hash=enrolled.tx_hash,
                block_number=enrolled.block_number,
            )
        if not client.is_registered(owner.eoa_address):
            commitment = bytes.fromhex(first_key.commitment.removeprefix("0x"))
            result = client.register(owner_eoa_account(owner), commitment)
            step(register_tx=result.tx_hash, registered_block=result.block_number)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.REGISTERED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                detail={"key_id": first_key.key_id, "commitment": first_key.commitment},
            )
            OwnerKey.objects.filter(pk=first_key.pk).update(
                chain_state=ChainState.CONFIRMED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
            )
        else:
            OwnerKey.objects.filter(pk=first_key.pk).update(chain_state=ChainState.CONFIRMED)
        step(chain_state=ChainState.CONFIRMED, chain_error="")
        owner.refresh_from_db()
    # Read back what is on chain now: the commitment of the key the portal holds.
    owner_identity_check(owner=owner, fresh=True)
    # Keys rotated, robots paired (and records uploaded) while registration was pending can go.
    for key in owner.keys.filter(chain_state=ChainState.PENDING):
        enqueue("accounts.tasks.key_rotate", key.pk)
    robots = Robot.objects.filter(owner=owner, key_chain_state=ChainState.PENDING)
    for robot_id in robots.values_list("pk", flat=True):
        enqueue("accounts.tasks.robot_key_register", str(robot_id))
    owner_chain_ready(owner.pk)
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
    chain_work_check()  # nothing goes to a reset chain
    with exclusive(f"owner:{owner.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        client = chain_client()
        commitment = bytes.fromhex(key.commitment.removeprefix("0x"))
        fields: dict[str, object] = {"chain_state": ChainState.CONFIRMED}
        if client.commitment_of(owner.eoa_address) != commitment:
            try:
                result = client.rotate_key(owner_eoa_account(owner), commitment)
            except InsufficientFunds:
                # Waits for gas, using up nothing: the task retries and the sweep queues it again.
                enqueue("accounts.tasks.owner_top_up", owner.pk)
                raise
            fields.update(tx_hash=result.tx_hash, block_number=result.block_number)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.KEY_ROTATED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                detail={"key_id": key.key_id, "commitment": key.commitment},
            )
        OwnerKey.objects.filter(pk=key.pk).update(**fields)
    key.refresh_from_db()
    owner_identity_check(owner=owner, fresh=True)
    return key


def chain_work_sweep() -> dict[str, int]:
    """Queue again registrations, key rotations, and robots' keys and their revocations
    pending for longer than ANCHOR_STALE_AFTER (a lost message, a dead worker, a registration
    waiting for the funding budget); their tasks are idempotent. Sign-ups awaiting or refused
    an operator's approval stay put."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    registrations = Owner.objects.filter(
        chain_state=ChainState.PENDING, created_at__lt=cutoff, approval=Approval.APPROVED
    )
    keys = OwnerKey.objects.filter(
        chain_state=ChainState.PENDING,
        created_at__lt=cutoff,
        owner__chain_state=ChainState.CONFIRMED,
    )
    robot_keys = Robot.objects.filter(
        key_chain_state=ChainState.PENDING,
        paired_at__lt=cutoff,
        owner__chain_state=ChainState.CONFIRMED,
    )
    # A revocation also waits for the records its key signed (robot_key_revoke_on_chain).
    revocations = Robot.objects.filter(
        key_revoke_state=ChainState.PENDING,
        key_chain_state=ChainState.CONFIRMED,
        revoked_at__lt=cutoff,
    )
    return {
        "registrations": _queue_again("accounts.tasks.owner_register", registrations),
        "keys": _queue_again("accounts.tasks.key_rotate", keys),
        "robot_keys": _queue_again("accounts.tasks.robot_key_register", robot_keys),
        "robot_key_revocations": _queue_again("accounts.tasks.robot_key_revoke", revocations),
        "top_ups": gas_sweep(),
    }


def _queue_again(task_name: str, rows: QuerySet) -> int:
    """Queue `task_name` for each of these rows, by primary key (a robot's as text); how many."""
    pks = list(rows.values_list("pk", flat=True))
    for pk in pks:
        enqueue(task_name, str(pk) if isinstance(pk, uuid.UUID) else pk)
    return len(pks)


def owners_reconcile(*, owners: Sequence[Owner]) -> dict[str, int]:
    """Put back on chain what the chain lost of these owners' registration and keys.

    A confirmed owner the chain does not know as enrolled and registered goes back to pending
    with its keys, and owner_register is queued (it skips what is on chain, then its later keys
    are rotated in order). When the commitment on chain is an older key's than the newest
    confirmed one (rotations lost), the keys after it go back to pending and key_rotate is
    queued for each. Any other commitment on chain is the identity check's business: it is
    called, and records the mismatch. Their robots' keys are robot_keys_reconcile's.
    """
    client = chain_client()
    counts = {"owners_checked": 0, "registrations_lost": 0, "rotations_lost": 0, "mismatches": 0}
    for owner in owners:
        if owner.chain_state != ChainState.CONFIRMED:
            continue
        counts["owners_checked"] += 1
        eoa = owner.eoa_address
        if not (client.is_enrolled(eoa) and client.is_registered(eoa)):
            _owner_registration_redo(client, owner)
            counts["registrations_lost"] += 1
            continue
        on_chain = "0x" + client.commitment_of(eoa).hex()
        keys = list(owner.keys.order_by("created_at", "pk"))
        commitments = [key.commitment.lower() for key in keys]
        confirmed = [i for i, key in enumerate(keys) if key.chain_state == ChainState.CONFIRMED]
        if not confirmed or on_chain == commitments[confirmed[-1]]:
            continue
        if on_chain in commitments[: confirmed[-1]]:
            _key_rotations_redo(client, owner, keys[commitments.index(on_chain) + 1 :])
            counts["rotations_lost"] += 1
            continue
        try:
            owner_identity_check(owner=owner, fresh=True)
        except IdentityMismatch:
            counts["mismatches"] += 1
    return counts


def owners_chain_reset() -> list[int]:
    """After a chain reset: every approved owner goes back to pending registration with all its
    keys (fund, enroll, register, then the later keys rotated in order), owner_register queued
    on commit for each. Their robots' confirmed keys and revocations go back to pending too:
    each registration queues its robots' keys, and each key its revocation (robot_keys.py).
    Returns their ids."""
    owners = Owner.objects.filter(approval=Approval.APPROVED).order_by("pk")
    ids = list(owners.values_list("pk", flat=True))
    with transaction.atomic():
        Owner.objects.filter(pk__in=ids).update(
            chain_state=ChainState.PENDING,
            chain_error="",
            fund_tx="",
            enroll_tx="",
            register_tx="",
            registered_block=None,
        )
        OwnerKey.objects.filter(owner_id__in=ids).update(
            chain_state=ChainState.PENDING, tx_hash="", block_number=None
        )
        robots = Robot.objects.filter(owner_id__in=ids)
        robots.filter(key_chain_state=ChainState.CONFIRMED).update(
            key_chain_state=ChainState.PENDING, key_added_block=None
        )
        robots.filter(key_revoke_state=ChainState.CONFIRMED).update(
            key_revoke_state=ChainState.PENDING
        )
        for owner_id in ids:
            transaction.on_commit(lambda o=owner_id: enqueue("accounts.tasks.owner_register", o))
    client = chain_client()
    for eoa in owners.values_list("eoa_address", flat=True):
        client.resync_nonce(eoa)  # counters of the chain before the reset mean nothing now
    return ids


def _owner_registration_redo(client: AuthROSChain, owner: Owner) -> None:
    with transaction.atomic():
        changed = Owner.objects.filter(pk=owner.pk, chain_state=ChainState.CONFIRMED).update(
            chain_state=ChainState.PENDING, chain_error=""
        )
        if changed:
            OwnerKey.objects.filter(owner=owner).update(chain_state=ChainState.PENDING)
            transaction.on_commit(lambda: enqueue("accounts.tasks.owner_register", owner.pk))
    # Counters of transactions the chain lost: the owner's, and the operator's (funding, enrolment).
    client.resync_nonce(owner.eoa_address)
    client.resync_nonce(operator_account().address)
    logger.warning("the chain lost the registration of %s: registering it again", owner)


def _key_rotations_redo(client: AuthROSChain, owner: Owner, keys: Sequence[OwnerKey]) -> None:
    with transaction.atomic():
        OwnerKey.objects.filter(pk__in=[key.pk for key in keys]).update(
            chain_state=ChainState.PENDING
        )
        for key in keys:
            transaction.on_commit(lambda k=key.pk: enqueue("accounts.tasks.key_rotate", k))
    client.resync_nonce(owner.eoa_address)
    logger.warning("the chain lost %d key rotation(s) of %s: rotating again", len(keys), owner)
