"""Robots' signing keys on chain (DESIGN.md "Provenance"), run by the worker: a paired robot's
SM2 public key registered by its owner's EOA (robotKeyAdd) once the pairing is approved, and
revoked (robotKeyRevoke) once the robot is unpaired.

A key waits for its owner's registration; a revocation waits for the key and for the records
the key signed to be anchored, since a record anchored in or after the revocation's block is
not genuine ("A record is genuine"). Once a key is confirmed, the work that waited for it in
the apps above accounts (sharing's anchoring) is started through registration's
owner_chain_ready, and those apps say through robot_key_revoke_wait_register which records
still wait. The sweep, the reconciliation and a chain reset (registration.py) queue again
what was lost.

A key belongs to the owner who registered it (issue 46): the contract keeps each owner's
registration apart (robotKeyOfOwner), and here a pairing that names a key another owner has,
in the portal or first on chain, is refused (robot_key_claimed_elsewhere), and the
reconciliation's finding that the chain names another first owner is told
(robot_key_disputed): the apps above accounts register what to do with it (sharing writes a
SecurityEvent and alerts the owner).
"""

import logging
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from django.conf import settings
from django.db import transaction

from accounts.models import ChainActivity, ChainState, Owner, Robot
from accounts.selectors import owner_eoa_account
from accounts.services.activity import chain_activity_record
from accounts.services.registration import owner_chain_ready
from chainworker.codec import RobotKeyOnChain, TxResult
from chainworker.errors import ChainError, InsufficientFunds, TransactionReverted
from chainworker.selectors import operator_alert_open
from chainworker.services import (
    chain_client,
    chain_work_check,
    operator_alert_raise,
    operator_alert_resolve,
)
from chainworker.work import ChainWorkNotReady, exclusive
from core.outbox import enqueue

logger = logging.getLogger(__name__)

# Asked whether records a robot's key signed still wait to be anchored (an app above accounts
# registers it when Django starts, as with owner_chain_ready_listener_register).
SignedRecordsWaiting = Callable[[Robot], bool]

_revoke_waits: list[SignedRecordsWaiting] = []

# The operator alert (chainworker OperatorAlert) of a robot whose key the chain names another
# first owner of; its subject is "robot <id>".
ROBOT_KEY_DISPUTED_ALERT = "robot-key-disputed"


@dataclass(frozen=True)
class RobotKeyDispute:
    """A robot key two owners claim. `where`: "pairing" (an approval naming a key another owner
    has was refused) or "chain" (robotKeyOf names `claimant_eoa` as the first to register the
    key of `owner`'s robot: blocks lost, or a registration made outside this portal). `owner`
    is whose the key is in this portal (the one told), `robot` its robot; for a pairing whose
    key only the chain knows, `owner` is the approver and `robot` None."""

    where: str
    owner: Owner
    key_hash: str
    robot: Robot | None
    claimant_eoa: str


RobotKeyDisputeListener = Callable[[RobotKeyDispute], None]

_dispute_listeners: list[RobotKeyDisputeListener] = []


def robot_key_dispute_listener_register(listener: RobotKeyDisputeListener) -> None:
    """Have `listener(dispute)` called for each robot key dispute found (an app above accounts
    registers it when Django starts, as with owner_chain_ready_listener_register)."""
    if listener not in _dispute_listeners:
        _dispute_listeners.append(listener)


def robot_key_disputed(dispute: RobotKeyDispute) -> None:
    """Tell the registered listeners of a dispute (once per finding: callers hold back a
    repeat)."""
    for listener in _dispute_listeners:
        listener(dispute)


def robot_key_claimed_elsewhere(*, owner: Owner, key_hash: str) -> RobotKeyDispute | None:
    """The dispute if `owner` pairing a robot with this key would claim another owner's key:
    a robot of another owner in the portal has it (whatever its state: a key stays its
    owner's), or robotKeyOf names another EOA as its first owner. The chain is not asked when
    it cannot be read: the worker then adds the key under this owner alone (robotKeyOfOwner),
    which no other owner's registration touches, and the reconciliation looks again."""
    other = (
        Robot.objects.filter(key_hash=key_hash)
        .exclude(owner=owner)
        .select_related("owner__user")
        .order_by("created_at")
        .first()
    )
    if other is not None:
        return RobotKeyDispute(
            where="pairing",
            owner=other.owner,
            key_hash=key_hash,
            robot=other,
            claimant_eoa=owner.eoa_address,
        )
    try:
        first = chain_client().robot_key_of(bytes.fromhex(key_hash))
    except ChainError as exc:
        logger.warning("robot key %s: the chain cannot be asked whose it is: %s", key_hash, exc)
        return None
    if first.owner is None or first.owner.lower() == owner.eoa_address.lower():
        return None
    return RobotKeyDispute(
        where="pairing", owner=owner, key_hash=key_hash, robot=None, claimant_eoa=first.owner
    )


def robot_key_revoke_wait_register(check: SignedRecordsWaiting) -> None:
    """Have `check(robot)` asked before a robot's key is revoked on chain: while it answers
    true (records signed by the key are not anchored yet), the revocation waits."""
    if check not in _revoke_waits:
        _revoke_waits.append(check)


def robot_key_register_on_chain(*, robot_id: uuid.UUID | str) -> Robot:
    """Add the robot's public key on chain from its owner's EOA (robotKeyAdd), once the owner is
    registered; the key is then confirmed with the block it was added in.

    The key on chain already as this owner's (a run whose answer was lost) counts as added.
    Revoked by this owner while the robot is still paired (a key paired again after it was
    unpaired: an owner adds a key once), it can never count: the key is failed. Another
    owner's registration of the same key changes nothing here (robotKeyOfOwner)."""
    robot = Robot.objects.select_related("owner").get(pk=robot_id)
    owner = robot.owner
    if robot.key_chain_state != ChainState.PENDING:
        return robot
    if owner.chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"{owner} is not registered on chain yet")
    chain_work_check()  # nothing goes to a reset chain
    with exclusive(f"robot-key:{robot.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        robot.refresh_from_db()
        if robot.key_chain_state != ChainState.PENDING:
            return robot
        client = chain_client()
        key_hash = bytes.fromhex(robot.key_hash)
        try:
            result = client.robot_key_add(
                owner_eoa_account(owner), key_hash, bytes.fromhex(robot.public_key)[1:]
            )
            added_block: int | None = result.block_number
            _robot_key_activity_record(robot, result, "RobotKeyAdded")
        except InsufficientFunds:
            # Waits for gas, using up nothing: the task retries and the sweep queues it again.
            enqueue("accounts.tasks.owner_top_up", owner.pk)
            raise
        except TransactionReverted as exc:
            if exc.error_name == "NotRegistered":
                # The chain lost the owner's registration: the reconciliation sends it again.
                raise ChainWorkNotReady(f"{owner} is not registered on this chain") from exc
            if exc.error_name != "RobotKeyExists":
                raise
            on_chain = client.robot_key_of_owner(key_hash, owner=owner.eoa_address)
            added_block = on_chain.added_block if _added_for(robot, on_chain) else None
            if added_block is None:
                logger.error(
                    "robot %s: its key %s is on chain as %s's, revoked in block %s: it can "
                    "never be this robot's; pair the robot with a new key",
                    robot.pk,
                    robot.key_hash,
                    on_chain.owner,
                    on_chain.revoked_block,
                )
        state = ChainState.FAILED if added_block is None else ChainState.CONFIRMED
        Robot.objects.filter(pk=robot.pk, key_chain_state=ChainState.PENDING).update(
            key_chain_state=state, key_added_block=added_block
        )
    robot.refresh_from_db()
    if robot.key_chain_state == ChainState.CONFIRMED:
        owner_chain_ready(owner.pk)  # records that waited for the key can be anchored now
        robot_key_revocations_release(owner_id=owner.pk)
    return robot


_ROBOT_KEY_KINDS = {
    "RobotKeyAdded": ChainActivity.Kind.ROBOT_KEY_ADDED,
    "RobotKeyRevoked": ChainActivity.Kind.ROBOT_KEY_REVOKED,
}


def _robot_key_activity_record(robot: Robot, result: TxResult, event_name: str) -> None:
    """The audit page's entry of the robot key's addition or revocation, from the event its
    transaction's receipt holds (RobotKeyAdded, RobotKeyRevoked): as grants' are recorded."""
    for event in result.events:
        if event.name == event_name:
            chain_activity_record(
                owner=robot.owner,
                kind=_ROBOT_KEY_KINDS[event_name],
                tx_hash=result.tx_hash,
                block_number=event.block_number,
                detail={
                    "robot_id": str(robot.pk),
                    "robot": robot.name,
                    "key_hash": bytes(event.args["keyHash"]).hex(),
                },
            )


def _added_for(robot: Robot, on_chain: RobotKeyOnChain) -> bool:
    """Whether the key on chain is this robot's, added by its owner: live, or revoked while the
    robot is being unpaired (that revocation is then found done)."""
    if on_chain.owner is None or on_chain.owner.lower() != robot.owner.eoa_address.lower():
        return False
    return on_chain.revoked_block is None or bool(robot.key_revoke_state)


def robot_key_revoke_on_chain(*, robot_id: uuid.UUID | str) -> Robot:
    """Revoke the unpaired robot's key on chain from its owner's EOA (robotKeyRevoke), once the
    key is on chain and the records it signed are anchored.

    Already revoked counts as done. A key the chain does not know (it lost the key's block) goes
    back to pending and is added again, which queues this revocation once it is. A key another
    EOA added cannot be revoked by this owner: the revocation is failed."""
    robot = Robot.objects.select_related("owner").get(pk=robot_id)
    owner = robot.owner
    if robot.key_revoke_state != ChainState.PENDING:
        return robot
    if robot.key_chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"the key of robot {robot.pk} is not on chain yet")
    if _signed_records_wait(robot):
        raise ChainWorkNotReady(f"records signed by robot {robot.pk} are not anchored yet")
    chain_work_check()  # nothing goes to a reset chain
    key_lost = False
    with exclusive(f"robot-key:{robot.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        robot.refresh_from_db()
        if robot.key_revoke_state != ChainState.PENDING:
            return robot
        state = ChainState.CONFIRMED
        try:
            result = chain_client().robot_key_revoke(
                owner_eoa_account(owner), bytes.fromhex(robot.key_hash)
            )
            _robot_key_activity_record(robot, result, "RobotKeyRevoked")
        except InsufficientFunds:
            enqueue("accounts.tasks.owner_top_up", owner.pk)
            raise
        except TransactionReverted as exc:
            if exc.error_name == "RobotKeyUnknown":
                key_lost = True
            elif exc.error_name == "NotRobotKeyOwner":  # a deployment from before issue 46
                logger.error(
                    "robot %s: its key %s was added on chain by another EOA than %s's: "
                    "it cannot be revoked by it",
                    robot.pk,
                    robot.key_hash,
                    owner,
                )
                state = ChainState.FAILED
            elif exc.error_name != "RobotKeyAlreadyRevoked":
                raise
        if not key_lost:
            Robot.objects.filter(pk=robot.pk, key_revoke_state=ChainState.PENDING).update(
                key_revoke_state=state
            )
    if key_lost:
        # Added again outside the lock: the addition, once confirmed, queues this revocation.
        with transaction.atomic():
            if Robot.objects.filter(pk=robot.pk, key_chain_state=ChainState.CONFIRMED).update(
                key_chain_state=ChainState.PENDING, key_added_block=None
            ):
                transaction.on_commit(
                    lambda: enqueue("accounts.tasks.robot_key_register", str(robot.pk))
                )
        logger.warning("the chain lost the key of robot %s: adding it again", robot.pk)
    robot.refresh_from_db()
    return robot


def robot_key_revocations_release(*, owner_id: int) -> int:
    """Queue the revocations of the owner's robots' keys that may go now: the key is on chain
    and the records it signed are anchored (the unpairing, a key's confirmation and the
    anchoring of records call this). How many were queued."""
    waiting = Robot.objects.filter(
        owner_id=owner_id,
        key_revoke_state=ChainState.PENDING,
        key_chain_state=ChainState.CONFIRMED,
    )
    ready = [robot.pk for robot in waiting if not _signed_records_wait(robot)]
    for robot_id in ready:
        enqueue("accounts.tasks.robot_key_revoke", str(robot_id))
    return len(ready)


def _signed_records_wait(robot: Robot) -> bool:
    return any(check(robot) for check in _revoke_waits)


def robot_keys_reconcile(*, owners: Sequence[Owner]) -> dict[str, int]:
    """The confirmed robot keys of these owners read back as each owner registered them
    (robotKeyOfOwner): a key the chain does not know goes back to pending (its confirmed
    revocation with it) and robot_key_register is queued (it queues the revocation once the
    key is back); a confirmed revocation the chain does not show goes back to pending and
    robot_key_revoke is queued.

    A live key whose first owner on chain (robotKeyOf) is another EOA is a dispute: what this
    portal checks holds (robotKeyOfOwner), but a reader of robotKeyOf alone would take the
    robot's records for the other's. It is told once (robot_key_disputed: a SecurityEvent and
    the owner's alert) and kept as an operator alert while the key is live."""
    robots = list(
        Robot.objects.filter(
            owner__in=[owner for owner in owners if owner.chain_state == ChainState.CONFIRMED],
            key_chain_state=ChainState.CONFIRMED,
        ).select_related("owner__user")
    )
    client = chain_client()
    lost_keys: list[Robot] = []
    lost_revocations: list[Robot] = []
    disputed = 0
    for robot in robots:
        key_hash = bytes.fromhex(robot.key_hash)
        on_chain = client.robot_key_of_owner(key_hash, owner=robot.owner.eoa_address)
        if on_chain.owner is None:
            lost_keys.append(robot)
        elif robot.key_revoke_state == ChainState.CONFIRMED and on_chain.revoked_block is None:
            lost_revocations.append(robot)
        subject = f"robot {robot.pk}"
        if robot.key_revoke_state:  # unpaired: what readers make of the key matters no more
            operator_alert_resolve(kind=ROBOT_KEY_DISPUTED_ALERT, subject=subject)
            continue
        first = client.robot_key_of(key_hash).owner
        if first is not None and first.lower() != robot.owner.eoa_address.lower():
            disputed += 1
            _robot_key_chain_dispute(robot, first_owner=first, subject=subject)
    with transaction.atomic():
        for robot in lost_keys:
            fields: dict[str, object] = {
                "key_chain_state": ChainState.PENDING,
                "key_added_block": None,
            }
            if robot.key_revoke_state == ChainState.CONFIRMED:
                fields["key_revoke_state"] = ChainState.PENDING
            # Only rows still as we read them: one confirmed again meanwhile is left alone.
            if Robot.objects.filter(pk=robot.pk, key_chain_state=ChainState.CONFIRMED).update(
                **fields
            ):
                transaction.on_commit(
                    lambda r=str(robot.pk): enqueue("accounts.tasks.robot_key_register", r)
                )
        for robot in lost_revocations:
            if Robot.objects.filter(pk=robot.pk, key_revoke_state=ChainState.CONFIRMED).update(
                key_revoke_state=ChainState.PENDING
            ):
                transaction.on_commit(
                    lambda r=str(robot.pk): enqueue("accounts.tasks.robot_key_revoke", r)
                )
    # A chain that lost blocks lost the owners' transactions too: count from the node.
    for eoa in sorted({robot.owner.eoa_address for robot in [*lost_keys, *lost_revocations]}):
        client.resync_nonce(eoa)
    if lost_keys or lost_revocations:
        logger.warning(
            "the chain lost %d robot key(s) and %d revocation(s): sending them again",
            len(lost_keys),
            len(lost_revocations),
        )
    return {
        "robot_keys_checked": len(robots),
        "robot_keys_lost": len(lost_keys),
        "robot_key_revocations_lost": len(lost_revocations),
        "robot_keys_disputed": disputed,
    }


def _robot_key_chain_dispute(robot: Robot, *, first_owner: str, subject: str) -> None:
    """The operator alert of a robot whose key's first owner on chain is another EOA, and, the
    first time it is seen, the dispute told (robot_key_disputed)."""
    seen = operator_alert_open(kind=ROBOT_KEY_DISPUTED_ALERT, subject=subject) is not None
    operator_alert_raise(
        kind=ROBOT_KEY_DISPUTED_ALERT,
        subject=subject,
        detail={
            "owner": robot.owner.username,
            "robot": robot.name,
            "key_hash": robot.key_hash,
            "first_owner_on_chain": first_owner,
        },
    )
    if not seen:
        robot_key_disputed(
            RobotKeyDispute(
                where="chain",
                owner=robot.owner,
                key_hash=robot.key_hash,
                robot=robot,
                claimant_eoa=first_owner,
            )
        )
