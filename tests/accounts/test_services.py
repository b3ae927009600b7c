"""Owners, keys and robots: what the services write, and what they refuse."""

import pytest
from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError
from django.db import connection

from accounts import keywrap
from accounts.agent_config import Topic
from accounts.errors import (
    InvalidKeyMaterial,
    InvalidUsername,
    KeyAlreadyUsed,
    RobotNameTaken,
    UsernameTaken,
    WeakPassword,
)
from accounts.models import DEFAULT_TOPICS, ChainState, Owner, OwnerKey, Robot
from accounts.selectors import (
    owner_eoa_account,
    owner_key_bytes,
    owner_key_current,
    robot_by_token,
    robot_topics,
)
from accounts.services.keys import key_rotate
from accounts.services.owners import owner_create
from accounts.services.registration import owner_register_on_chain
from accounts.services.robots import robot_create, robot_token_revoke
from sharing.services import anchoring
from smcrypto import key_commitment, key_id, sm4
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


def test_owner_is_registered_on_chain_with_its_key_commitment(make_owner, deployed):
    key = sm4.generate_key()
    owner = make_owner("alice", key=key)
    assert owner.chain_state == ChainState.CONFIRMED
    assert owner.fund_tx and owner.enroll_tx and owner.register_tx  # noqa: PT018
    assert deployed.is_registered(owner.eoa_address)
    assert deployed.commitment_of(owner.eoa_address) == key_commitment(owner.eoa_address, key)
    assert deployed.balance(owner.eoa_address) > 0
    current = owner_key_current(owner)
    assert current.key_id == key_id(key).hex()
    assert current.chain_state == ChainState.CONFIRMED
    assert owner_key_bytes(current) == key
    assert owner_eoa_account(owner).address == owner.eoa_address


def test_registration_is_idempotent(make_owner, deployed):
    owner = make_owner()
    Owner.objects.filter(pk=owner.pk).update(chain_state=ChainState.PENDING)
    again = owner_register_on_chain(owner_id=owner.pk)
    assert again.chain_state == ChainState.CONFIRMED
    assert [e.name for e in deployed.events(names=["Registered"])] == ["Registered"]


def test_a_confirmed_registration_queues_the_anchoring_of_its_owners_records(
    make_owner, monkeypatch
):
    """Records uploaded while the registration was pending go once it is confirmed: sharing's
    listener (registered by sharing/apps.py) queues a run for the owner."""
    owner = make_owner()
    queued: list[tuple[object, ...]] = []
    monkeypatch.setattr(anchoring, "enqueue", lambda *args, **kwargs: queued.append(args) or True)
    Owner.objects.filter(pk=owner.pk).update(chain_state=ChainState.PENDING)
    owner_register_on_chain(owner_id=owner.pk)
    assert queued == [("sharing.tasks.records_anchor", owner.pk)]


def test_secrets_are_not_stored_in_plaintext(make_owner):
    key = sm4.generate_key()
    owner = make_owner("bob", key=key)
    eoa_key = bytes(owner_eoa_account(owner).key)
    user = get_user_model().objects.get(username="bob")
    assert TEST_PASSWORD not in user.password
    with connection.cursor() as cursor:
        dumps = []
        for table in ("accounts_owner", "accounts_ownerkey", "auth_user"):
            cursor.execute(f"SELECT * FROM {table}")  # noqa: S608 (fixed table names)
            dumps.extend(repr(row) for row in cursor.fetchall())
            cursor.execute(f"SELECT * FROM {table}")  # noqa: S608
            for row in cursor.fetchall():
                for value in row:
                    raw = bytes(value) if isinstance(value, bytes | memoryview) else b""
                    assert key not in raw
                    assert eoa_key not in raw
    text = "\n".join(dumps)
    assert key.hex() not in text
    assert eoa_key.hex() not in text
    assert TEST_PASSWORD not in text


def test_wrapped_secrets_need_the_master_key_and_their_purpose(make_owner, settings):
    owner = make_owner()
    stored = OwnerKey.objects.get(owner=owner)
    with pytest.raises(keywrap.UnwrapFailed):
        keywrap.unwrap(stored.key_wrapped, purpose="sm4-key:999:0000")
    settings.AUTHROS_MASTER_KEY = sm4.generate_key().hex()
    with pytest.raises(keywrap.UnwrapFailed):
        owner_key_bytes(stored)


def test_master_key_file_is_private(make_owner, settings):
    make_owner()
    mode = (settings.SECRETS_DIR / "master.key").stat().st_mode & 0o777
    assert mode == 0o600


@pytest.mark.parametrize(
    ("username", "password", "key", "error"),
    [
        ("carol", "short", None, WeakPassword),
        ("carol", "password", None, WeakPassword),
        ("bad name!", TEST_PASSWORD, None, InvalidUsername),
        ("", TEST_PASSWORD, None, InvalidUsername),
        ("carol", TEST_PASSWORD, b"too short", InvalidKeyMaterial),
        ("carol", TEST_PASSWORD, bytes(16), InvalidKeyMaterial),
    ],
)
def test_owner_create_refusals_change_nothing(deployed, username, password, key, error):
    with pytest.raises(error):
        owner_create(username=username, password=password, sm4_key=key or sm4.generate_key())
    assert Owner.objects.count() == 0
    assert get_user_model().objects.count() == 0


def test_username_taken(make_owner):
    make_owner("dave")
    with pytest.raises(UsernameTaken):
        owner_create(username="dave", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    assert Owner.objects.count() == 1


def test_key_rotation_reaches_the_chain(make_owner, deployed, django_capture_on_commit_callbacks):
    old = sm4.generate_key()
    owner = make_owner(key=old)
    new = sm4.generate_key()
    with django_capture_on_commit_callbacks(execute=True):
        rotated = key_rotate(owner=owner, sm4_key=new)
    rotated.refresh_from_db()
    assert rotated.is_current
    assert rotated.chain_state == ChainState.CONFIRMED
    assert rotated.tx_hash
    assert deployed.commitment_of(owner.eoa_address) == key_commitment(owner.eoa_address, new)
    previous = OwnerKey.objects.get(owner=owner, key_id=key_id(old).hex())
    assert not previous.is_current
    assert previous.retired_at is not None
    assert owner_key_bytes(previous) == old
    with pytest.raises(KeyAlreadyUsed):
        key_rotate(owner=owner, sm4_key=old)


def test_robot_token_is_shown_once_and_stored_hashed(make_owner):
    owner = make_owner()
    robot, token = robot_create(owner=owner, name="turtlebot")
    assert len(token) >= 40
    stored = Robot.objects.get(pk=robot.pk)
    assert token not in stored.token_hash
    assert stored.token_prefix == token[:8]
    assert robot_by_token(token) == robot
    assert robot_by_token(token + "x") is None
    with pytest.raises(RobotNameTaken):
        robot_create(owner=owner, name="turtlebot")
    robot_token_revoke(robot=robot)
    assert robot_by_token(token) is None


@pytest.fixture
def unregistered_owner(db) -> Owner:
    """An owner whose chain work never runs: enough for robots."""
    return owner_create(username="rita", password=TEST_PASSWORD, sm4_key=sm4.generate_key())


def test_robot_keeps_the_topics_it_was_created_with(unregistered_owner):
    owner = unregistered_owner
    topics = [
        Topic("/scan", "sensor_msgs/LaserScan"),
        Topic("~odom", "nav_msgs/Odometry"),
    ]
    robot, _token = robot_create(owner=owner, name="lidar", topics=topics)
    stored = Robot.objects.get(pk=robot.pk)
    assert stored.topics == [
        {"name": "/scan", "type": "sensor_msgs/LaserScan"},
        {"name": "~odom", "type": "nav_msgs/Odometry"},
    ]
    assert robot_topics(stored) == tuple(topics)
    default, _token = robot_create(owner=owner, name="sim")
    assert robot_topics(default) == DEFAULT_TOPICS


@pytest.mark.parametrize(
    ("topics", "message"),
    [
        ([], "at least one topic"),
        ([Topic("/a", "String")], "must be package/Message"),
        ([Topic("not a topic", "std_msgs/String")], "not a valid ROS topic name"),
        ([Topic("/a", "std_msgs/String")] * 2, "topics listed twice"),
    ],
)
def test_robot_with_invalid_topics_is_refused(unregistered_owner, topics, message):
    with pytest.raises(ValidationError, match=message):
        robot_create(owner=unregistered_owner, name="r", topics=topics)
    assert not Robot.objects.exists()


@pytest.mark.parametrize(
    "value",
    [
        "/robot/odom nav_msgs/Odometry",
        [{"name": "/a"}],
        [{"name": "/a", "type": "std_msgs/String", "rate": 10}],
        [["/a", "std_msgs/String"]],
    ],
)
def test_robot_topics_field_takes_only_a_list_of_name_and_type(unregistered_owner, value):
    robot, _token = robot_create(owner=unregistered_owner, name="r")
    robot.topics = value
    with pytest.raises(ValidationError) as refused:
        robot.full_clean()
    assert "topics" in refused.value.message_dict
