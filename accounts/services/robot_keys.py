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
"""

import logging
import uuid
from collections.abc import Callable

from django.conf import settings
from django.db import transaction

from accounts.models import ChainState, Robot
from accounts.selectors import owner_eoa_account
from accounts.services.registration import owner_chain_ready
from chainworker.codec import RobotKeyOnChain
from chainworker.errors import InsufficientFunds, TransactionReverted
from chainworker.services import chain_client, chain_work_check
from chainworker.work import ChainWorkNotReady, exclusive
from core.outbox import enqueue

logger = logging.getLogger(__name__)

# Asked whether records a robot's key signed still wait to be anchored (an app above accounts
# registers it when Django starts, as with owner_chain_ready_listener_register).
SignedRecordsWaiting = Callable[[Robot], bool]

_revoke_waits: list[SignedRecordsWaiting] = []


def robot_key_revoke_wait_register(check: SignedRecordsWaiting) -> None:
    """Have `check(robot)` asked before a robot's key is revoked on chain: while it answers
    true (records signed by the key are not anchored yet), the revocation waits."""
    if check not in _revoke_waits:
        _revoke_waits.append(check)


def robot_key_register_on_chain(*, robot_id: uuid.UUID | str) -> Robot:
    """Add the robot's public key on chain from its owner's EOA (robotKeyAdd), once the owner is
    registered; the key is then confirmed with the block it was added in.

    The key on chain already as this owner's (a run whose answer was lost) counts as added. As
    another owner's, or revoked while the robot is still paired (a key paired again after it
    was unpaired: the chain adds a key once), it can never count: the key is failed."""
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
            on_chain = client.robot_key_of(key_hash)
            added_block = on_chain.added_block if _added_for(robot, on_chain) else None
            if added_block is None:
                logger.error(
                    "robot %s: its key %s is on chain as %s's (revoked in block %s): it can "
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
            chain_client().robot_key_revoke(owner_eoa_account(owner), bytes.fromhex(robot.key_hash))
        except InsufficientFunds:
            enqueue("accounts.tasks.owner_top_up", owner.pk)
            raise
        except TransactionReverted as exc:
            if exc.error_name == "RobotKeyUnknown":
                key_lost = True
            elif exc.error_name == "NotRobotKeyOwner":
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
