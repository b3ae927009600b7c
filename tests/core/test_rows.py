"""FixedSelect, the hot path's reads written once: the same instances as the ORM's, its
converters applied (UUIDs, datetimes, JSON, booleans), related objects joined and cached."""

import uuid

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from accounts.models import OwnerKey, Robot
from accounts.selectors import owner_keys, robot_by_token, robot_token_hash
from accounts.services import key_rotate, robot_token_revoke
from sharing.anchoring import records_anchor
from sharing.deletion import record_delete
from sharing.models import Record
from sharing.selectors import record_to_check, record_to_open
from sharing.services import record_create
from smcrypto import sm4

pytestmark = pytest.mark.django_db


def fields_of(instance) -> dict[str, object]:
    return {
        field.attname: getattr(instance, field.attname) for field in instance._meta.concrete_fields
    }


def test_a_robot_by_its_token_is_the_orms_robot_with_its_owner_and_user(make_robot):
    setup = make_robot("alice")
    Robot.objects.filter(pk=setup.robot.pk).update(
        topics=[{"name": "/odom", "type": "nav_msgs/Odometry"}]
    )
    expected = Robot.objects.select_related("owner__user").get(pk=setup.robot.pk)

    with CaptureQueriesContext(connection) as queries:
        robot = robot_by_token(setup.token)
        owner, user = robot.owner, robot.owner.user  # joined: no further query
    assert len(queries) == 1
    assert fields_of(robot) == fields_of(expected)
    assert fields_of(owner) == fields_of(expected.owner)
    assert fields_of(user) == fields_of(expected.owner.user)
    assert robot.topics[0]["name"] == "/odom"
    assert robot.created_at.tzinfo is not None
    assert robot.is_active is True
    assert (robot._state.adding, robot._state.db) == (False, "default")


def test_an_unknown_or_revoked_token_finds_no_robot(make_robot):
    setup = make_robot("alice")
    assert robot_by_token(setup.token + "x") is None
    assert robot_by_token("' OR 1=1 --") is None
    robot_token_revoke(robot=setup.robot)
    assert robot_by_token(setup.token) is None
    assert Robot.objects.filter(token_hash=robot_token_hash(setup.token)).exists()


def test_an_owners_keys_are_the_orms_newest_first_with_the_owner_cached(make_robot):
    setup = make_robot("alice")
    key_rotate(owner=setup.owner, sm4_key=sm4.generate_key())
    expected = list(OwnerKey.objects.filter(owner=setup.owner).order_by("-created_at", "-pk"))

    with CaptureQueriesContext(connection) as queries:
        keys = owner_keys(setup.owner)
        owners = {key.owner.pk for key in keys}
    assert len(queries) == 1
    assert [fields_of(key) for key in keys] == [fields_of(key) for key in expected]
    assert [key.is_current for key in keys] == [True, False]
    assert bytes(keys[0].key_wrapped) == bytes(expected[0].key_wrapped)
    assert owners == {setup.owner.pk}


def test_a_record_to_open_and_to_check_are_the_orms_with_nullable_keys_left_joined(
    make_robot, deployed
):
    setup = make_robot("alice")
    first, second = (record_create(robot=setup.robot, data=setup.seal(seq)) for seq in (1, 2))

    # Not anchored, not deleted: the nullable keys are None, read in the same query.
    with CaptureQueriesContext(connection) as queries:
        opened = record_to_open(first.pk)
        assert opened.deleted_by is None
        assert opened.owner.user.username == "alice"
        checked = record_to_check(first.pk)
        assert checked.anchor_root is None
    assert len(queries) == 2
    assert fields_of(opened) == fields_of(Record.objects.get(pk=first.pk))

    assert records_anchor(owner_id=setup.owner.pk) == 2
    record_delete(owner=setup.owner, record_id=second.pk, actor=setup.owner.user)
    for record_id in (first.pk, second.pk):
        expected = Record.objects.select_related("anchor_root", "deleted_by").get(pk=record_id)
        checked = record_to_check(str(record_id))
        assert fields_of(checked) == fields_of(expected)
        assert fields_of(checked.anchor_root) == fields_of(expected.anchor_root)
        opened = record_to_open(record_id)
        assert opened.deleted_by_id == expected.deleted_by_id
        if expected.deleted_by is not None:
            assert fields_of(opened.deleted_by) == fields_of(expected.deleted_by)
    assert record_to_open(second.pk).deleted_by.username == "alice"
    assert record_to_open(uuid.uuid4()) is None
    with pytest.raises(Record.DoesNotExist):
        record_to_check(uuid.uuid4())
