"""FixedSelect, the hot path's reads written once: the same instances as the ORM's, its
converters applied (UUIDs, datetimes, JSON, booleans), related objects joined and cached."""

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from accounts.models import OwnerKey, Robot
from accounts.selectors import owner_keys, robot_by_token, robot_token_hash
from accounts.services import key_rotate, robot_token_revoke
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
