"""Robots' signing keys on chain (DESIGN.md "Provenance"): approving a pairing adds the robot's
key from its owner's EOA, unpairing revokes it, both queued like every chain write; records
signed by a key not on chain yet wait before anchoring, and a revocation waits for the records
its key signed; the sweep, the reconciliation and a chain reset put back what was lost.

Tasks run inline (Celery eager). "Lost blocks" are the test node's snapshots reverted
(`blocks_lost`); a reset points CHAIN_RPC_URL at a new node (`fresh_chain`).
"""

import hashlib
from datetime import UTC, datetime

import pytest
from django.core.management import call_command

from accounts.models import ChainState, Owner, Robot
from accounts.selectors import owner_eoa_account
from accounts.services.owners import owner_close
from accounts.services.registration import chain_work_sweep, owner_register_on_chain
from accounts.services.robot_keys import robot_key_register_on_chain, robot_key_revoke_on_chain
from accounts.services.robots import robot_create, robot_token_revoke
from chainworker import services as chain_services
from chainworker.work import ChainWorkNotReady
from sharing.models import Record
from sharing.services.anchoring import records_anchor
from sharing.services.reconcile import chain_reconcile
from smcrypto.sm3 import sm3_hex

pytestmark = pytest.mark.django_db


def _key(robot: Robot) -> bytes:
    return bytes.fromhex(robot.key_hash)


def _public_key_xy(robot: Robot) -> bytes:
    return bytes.fromhex(robot.public_key)[1:]


def _record(robot: Robot, seq: int, *, signed: bool = True) -> Record:
    """A pending record of the robot as the upload stores it: signed by the robot's key, or
    unsigned (a robot added by hand)."""
    return Record.objects.create(
        owner=robot.owner,
        robot=robot,
        topic="/robot/odom",
        data_type="nav_msgs/Odometry",
        seq=seq,
        captured_at=datetime.now(tz=UTC),
        key_id="00" * 8,
        digest=hashlib.sha256(f"{robot.pk}/{seq}".encode()).hexdigest(),
        signer=robot.key_hash if signed else "",
        size=1,
        storage_name=f"{robot.pk}/{seq}",
    )


def _anchor(owner: Owner, on_commit) -> None:
    on_commit(lambda: records_anchor(owner_id=owner.pk))


def _assert_on_chain(robot: Robot, *, revoked: bool = False) -> None:
    robot.refresh_from_db()
    on_chain = chain_services.chain_client().robot_key_of_owner(
        _key(robot), owner=robot.owner.eoa_address
    )
    assert robot.key_chain_state == ChainState.CONFIRMED
    assert on_chain.owner == robot.owner.eoa_address
    assert on_chain.added_block == robot.key_added_block
    assert (on_chain.revoked_block is not None) == revoked
    assert robot.key_revoke_state == (ChainState.CONFIRMED if revoked else "")


# --- adding and revoking -----------------------------------------------------------------


def test_approving_a_pairing_registers_the_robots_key_from_the_owners_eoa(make_owner, pair_robot):
    owner = make_owner("alice")
    robot = pair_robot(owner).robot
    assert robot.key_hash == sm3_hex(_public_key_xy(robot))
    _assert_on_chain(robot)
    client = chain_services.chain_client()
    (added,) = client.events(names=["RobotKeyAdded"])
    assert added.args["owner"] == owner.eoa_address
    assert added.args["keyHash"] == _key(robot)
    assert added.args["publicKey"] == _public_key_xy(robot)
    assert added.block_number == robot.key_added_block


def test_a_robot_added_by_hand_has_no_key_on_chain(make_owner, on_commit):
    owner = make_owner("alice")
    robot, _token = robot_create(owner=owner, name="by-hand")
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    robot.refresh_from_db()
    assert (robot.key_hash, robot.key_chain_state, robot.key_revoke_state) == ("", "", "")
    assert chain_services.chain_client().events(names=["RobotKeyAdded", "RobotKeyRevoked"]) == []


def test_unpairing_revokes_the_key_on_chain(make_owner, pair_robot, on_commit):
    owner = make_owner("alice")
    robot = pair_robot(owner).robot
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    _assert_on_chain(robot, revoked=True)
    on_chain = chain_services.chain_client().robot_key_of(_key(robot))
    assert on_chain.revoked_block > on_chain.added_block


def test_closing_the_account_revokes_its_robots_keys_on_chain(make_owner, pair_robot, on_commit):
    owner = make_owner("alice")
    robots = [pair_robot(owner).robot, pair_robot(owner).robot]
    on_commit(lambda: owner_close(owner=owner, actor=owner.user))
    for robot in robots:
        _assert_on_chain(robot, revoked=True)


def test_a_key_waits_for_its_owners_registration(make_owner, pair_robot):
    owner = make_owner("alice")
    Owner.objects.filter(pk=owner.pk).update(chain_state=ChainState.PENDING)
    robot = pair_robot(owner, delivered=False).robot
    assert robot.key_chain_state == ChainState.PENDING
    with pytest.raises(ChainWorkNotReady, match="not registered on chain yet"):
        robot_key_register_on_chain(robot_id=robot.pk)

    # The registration's confirmation queues the keys that waited for it.
    owner_register_on_chain(owner_id=owner.pk)
    _assert_on_chain(robot)


def test_a_key_on_chain_already_as_this_owners_counts_as_added(make_owner, pair_robot):
    """A run whose answer was lost: robotKeyAdd is refused with RobotKeyExists, and robotKeyOf
    shows the owner's live key."""
    owner = make_owner("alice")
    robot = pair_robot(owner, delivered=False).robot
    client = chain_services.chain_client()
    added = client.robot_key_add(owner_eoa_account(owner), _key(robot), _public_key_xy(robot))
    robot_key_register_on_chain(robot_id=robot.pk)
    _assert_on_chain(robot)
    assert robot.key_added_block == added.block_number


def test_a_key_another_owner_added_first_is_still_added_for_its_owner(make_owner, pair_robot):
    """Issue 46: mallory registers alice's robot's key first (from outside the portal, or
    before lost blocks came back without alice's): alice's registration still goes through,
    under her own entry (robotKeyOfOwner), and robotKeyOf keeps mallory as the first owner."""
    owner, mallory = make_owner("alice"), make_owner("mallory")
    robot = pair_robot(owner, delivered=False).robot
    client = chain_services.chain_client()
    client.robot_key_add(owner_eoa_account(mallory), _key(robot), _public_key_xy(robot))
    robot = robot_key_register_on_chain(robot_id=robot.pk)
    _assert_on_chain(robot)
    assert client.robot_key_of(_key(robot)).owner == mallory.eoa_address


def test_a_key_revoked_before_fails_for_a_robot_paired_again_with_it(make_owner, pair_robot):
    """The chain adds a key once: a robot paired with a key revoked on chain cannot sign."""
    owner = make_owner("alice")
    robot = pair_robot(owner, delivered=False).robot
    client = chain_services.chain_client()
    account = owner_eoa_account(owner)
    client.robot_key_add(account, _key(robot), _public_key_xy(robot))
    client.robot_key_revoke(account, _key(robot))
    robot = robot_key_register_on_chain(robot_id=robot.pk)
    assert robot.key_chain_state == ChainState.FAILED


def test_a_key_waits_while_the_chain_lost_its_owners_registration(
    make_owner, pair_robot, blocks_lost
):
    with blocks_lost():
        owner = make_owner("alice")
    assert owner.chain_state == ChainState.CONFIRMED  # what the portal believes
    robot = pair_robot(owner, delivered=False).robot
    with pytest.raises(ChainWorkNotReady, match="not registered on this chain"):
        robot_key_register_on_chain(robot_id=robot.pk)
    robot.refresh_from_db()
    assert robot.key_chain_state == ChainState.PENDING


def test_a_revocation_waits_for_the_key(make_owner, pair_robot, on_commit):
    owner = make_owner("alice")
    robot = pair_robot(owner, delivered=False).robot
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    robot.refresh_from_db()
    assert (robot.key_chain_state, robot.key_revoke_state) == ("pending", "pending")
    with pytest.raises(ChainWorkNotReady, match="not on chain yet"):
        robot_key_revoke_on_chain(robot_id=robot.pk)

    # The key's confirmation queues the revocation that waited for it.
    robot_key_register_on_chain(robot_id=robot.pk)
    _assert_on_chain(robot, revoked=True)


def test_a_key_revoked_on_chain_already_counts_as_revoked(make_owner, pair_robot, on_commit):
    owner = make_owner("alice")
    robot = pair_robot(owner).robot
    chain_services.chain_client().robot_key_revoke(owner_eoa_account(owner), _key(robot))
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    _assert_on_chain(robot, revoked=True)
    assert len(chain_services.chain_client().events(names=["RobotKeyRevoked"])) == 1


def test_a_key_the_chain_lost_is_added_again_before_its_revocation(
    make_owner, pair_robot, on_commit, blocks_lost
):
    """robotKeyRevoke refused with RobotKeyUnknown: the key goes back to pending and is added
    again, which queues the revocation."""
    owner = make_owner("alice")
    with blocks_lost():
        robot = pair_robot(owner).robot
        _assert_on_chain(robot)
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    _assert_on_chain(robot, revoked=True)


def test_a_key_only_another_eoa_added_is_added_again_then_revoked(
    make_owner, pair_robot, on_commit
):
    """The portal holds the key as confirmed while the chain has only mallory's registration
    of it (a database restored over another chain's state): the revocation finds the key
    unknown for alice, adds it again under her, then revokes hers; mallory's stays."""
    owner, mallory = make_owner("alice"), make_owner("mallory")
    robot = pair_robot(owner, delivered=False).robot
    client = chain_services.chain_client()
    client.robot_key_add(owner_eoa_account(mallory), _key(robot), _public_key_xy(robot))
    Robot.objects.filter(pk=robot.pk).update(key_chain_state=ChainState.CONFIRMED)
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    _assert_on_chain(robot, revoked=True)
    assert client.robot_key_of(_key(robot)).owner == mallory.eoa_address
    assert client.robot_key_of(_key(robot)).revoked_block is None


# --- anchoring waits for the key, the revocation for the anchoring -------------------------


@pytest.mark.parametrize("mode", ["records", "root"])
def test_records_signed_by_a_key_not_on_chain_wait_and_go_once_it_is(
    make_owner, pair_robot, on_commit, settings, mode
):
    settings.ANCHOR_MODE = mode
    owner = make_owner("alice")
    robot = pair_robot(owner, delivered=False).robot
    by_hand, _token = robot_create(owner=owner, name="by-hand")
    signed, unsigned = _record(robot, 1), _record(by_hand, 1, signed=False)

    _anchor(owner, on_commit)

    # The unsigned record goes as before; the signed one waits, using up no attempt (and the
    # run queues no other run for it: inline, that would recurse until the key came).
    unsigned.refresh_from_db()
    signed.refresh_from_db()
    assert unsigned.status == Record.Status.ANCHORED
    assert (signed.status, signed.anchor_attempts, signed.failure_reason) == ("pending", 0, "")

    # The key's confirmation queues the owner's anchoring.
    robot_key_register_on_chain(robot_id=robot.pk)
    signed.refresh_from_db()
    robot.refresh_from_db()
    assert signed.status == Record.Status.ANCHORED
    assert chain_services.chain_client().robot_key_of(_key(robot)).live_at(signed.block_number)


def test_a_revocation_waits_for_the_records_its_key_signed(make_owner, pair_robot, on_commit):
    """A key revoked at or before a record's anchoring block would leave the record not
    genuine: the revocation goes once the records are anchored."""
    owner = make_owner("alice")
    robot = pair_robot(owner).robot
    record = _record(robot, 1)
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    robot.refresh_from_db()
    assert robot.key_revoke_state == ChainState.PENDING
    with pytest.raises(ChainWorkNotReady, match="not anchored yet"):
        robot_key_revoke_on_chain(robot_id=robot.pk)

    _anchor(owner, on_commit)  # the run queues the revocation that waited

    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    _assert_on_chain(robot, revoked=True)
    on_chain = chain_services.chain_client().robot_key_of(_key(robot))
    assert on_chain.live_at(record.block_number)


# --- what was lost is sent again -----------------------------------------------------------


def test_the_sweep_queues_again_keys_and_revocations_whose_message_was_lost(
    make_owner, pair_robot, django_capture_on_commit_callbacks, settings
):
    settings.ANCHOR_STALE_AFTER = 0
    # Owners of their own: a key's confirmation also queues its owner's waiting revocations.
    alice, carol, waiting = make_owner("alice"), make_owner("carol"), make_owner("bob")
    Owner.objects.filter(pk=waiting.pk).update(chain_state=ChainState.PENDING)
    robot, unpaired = pair_robot(alice, delivered=False).robot, pair_robot(carol).robot
    pair_robot(waiting, delivered=False)  # waits for its owner's registration: not queued
    with django_capture_on_commit_callbacks(execute=False):  # lost too
        robot_token_revoke(robot=unpaired, actor=carol.user)

    counts = chain_work_sweep()

    assert (counts["robot_keys"], counts["robot_key_revocations"]) == (1, 1)
    _assert_on_chain(robot)
    _assert_on_chain(unpaired, revoked=True)
    assert chain_work_sweep()["robot_keys"] == chain_work_sweep()["robot_key_revocations"] == 0


def test_keys_and_revocations_the_chain_lost_are_sent_again(
    make_owner, pair_robot, on_commit, blocks_lost
):
    owner = make_owner("alice")
    unpaired = pair_robot(owner).robot
    with blocks_lost():
        robot = pair_robot(owner).robot
        on_commit(lambda: robot_token_revoke(robot=unpaired, actor=owner.user))
        _assert_on_chain(robot)
        _assert_on_chain(unpaired, revoked=True)
    client = chain_services.chain_client()
    assert client.robot_key_of(_key(robot)).owner is None
    assert client.robot_key_of(_key(unpaired)).revoked_block is None

    counts = on_commit(chain_reconcile)

    assert (counts["robot_keys_lost"], counts["robot_key_revocations_lost"]) == (1, 1)
    _assert_on_chain(robot)
    _assert_on_chain(unpaired, revoked=True)
    again = on_commit(chain_reconcile)
    assert again["robot_keys_lost"] == again["robot_key_revocations_lost"] == 0


def _records_on_chain(records: list[Record]) -> None:
    """Each record anchored on the chain in use, and a signed one while its key was live."""
    client = chain_services.chain_client()
    for record in records:
        record.refresh_from_db()
        assert record.status == Record.Status.ANCHORED
        tree = record.anchor_root
        if tree is None:
            assert (
                client.data_query(record.id, owner=record.owner.eoa_address).digest.hex()
                == record.digest
            )
        else:
            assert client.root_of(tree.sender, bytes.fromhex(tree.root)).size == tree.size
        if record.signer:
            assert client.robot_key_of(bytes.fromhex(record.signer)).live_at(record.block_number)


@pytest.mark.parametrize("mode", ["records", "root"])
@pytest.mark.parametrize("how", ["reconcile", "chain_resync"])
def test_after_a_chain_reset_keys_are_added_and_revoked_again_around_their_records(
    make_owner, pair_robot, on_commit, fresh_chain, settings, mode, how
):
    """Every key is added again before the records it signed are anchored again, and a
    revoked key revoked again only after them: each record still verifies as signed."""
    settings.ANCHOR_MODE = mode
    owner = make_owner("alice")
    robot, unpaired = pair_robot(owner).robot, pair_robot(owner).robot
    by_hand, _token = robot_create(owner=owner, name="by-hand")
    records = [_record(robot, 1), _record(unpaired, 1), _record(by_hand, 1, signed=False)]
    _anchor(owner, on_commit)
    on_commit(lambda: robot_token_revoke(robot=unpaired, actor=owner.user))
    _records_on_chain(records)
    _assert_on_chain(unpaired, revoked=True)
    fresh_chain()

    if how == "reconcile":
        assert on_commit(chain_reconcile)["identity"] == "reset"
    else:
        on_commit(lambda: call_command("chain_resync", "--yes"))

    _assert_on_chain(robot)
    _assert_on_chain(unpaired, revoked=True)
    _records_on_chain(records)
    client = chain_services.chain_client()
    assert len(client.events(names=["RobotKeyAdded"])) == 2
    assert len(client.events(names=["RobotKeyRevoked"])) == 1
