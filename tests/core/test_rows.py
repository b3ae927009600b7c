"""FixedSelect, the hot path's reads written once: the same instances as the ORM's, its
converters applied (UUIDs, datetimes, JSON, booleans), related objects joined and cached; and
FixedInsert and FixedUpdate, an upload's writes, storing what the ORM's would."""

import re
import uuid

import pytest
from django.db import connection
from django.db.models.signals import post_init
from django.test.utils import CaptureQueriesContext

from accounts.models import OwnerKey, Robot
from accounts.selectors import owner_keys, robot_by_token, robot_token_hash
from accounts.services.keys import key_rotate
from accounts.services.robots import robot_token_revoke
from core.rows import FixedInsert, instances_made
from sharing.models import Record, Verdict
from sharing.selectors.records import record_to_open
from sharing.services.anchoring import records_anchor
from sharing.services.deletion import record_delete
from sharing.services.uploads import _ROBOT_SEQ_MOVE, record_create, record_create_batch
from sharing.verification.access import accesses_open
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


def test_a_record_to_open_is_the_orms_with_nullable_keys_left_joined(make_robot, deployed):
    setup = make_robot("alice")
    first, second = (record_create(robot=setup.robot, data=setup.seal(seq)) for seq in (1, 2))

    # Not anchored, not deleted: the nullable keys are None, read in the same query.
    with CaptureQueriesContext(connection) as queries:
        opened = record_to_open(first.pk)
        assert opened.deleted_by is None
        assert opened.owner.user.username == "alice"
    assert len(queries) == 1
    assert fields_of(opened) == fields_of(Record.objects.get(pk=first.pk))

    assert records_anchor(owner_id=setup.owner.pk) == 2
    record_delete(owner=setup.owner, record_id=second.pk, actor=setup.owner.user)
    for record_id in (first.pk, second.pk):
        expected = Record.objects.select_related("deleted_by").get(pk=record_id)
        opened = record_to_open(record_id)
        assert fields_of(opened) == fields_of(expected)
        assert opened.deleted_by_id == expected.deleted_by_id
        if expected.deleted_by is not None:
            assert fields_of(opened.deleted_by) == fields_of(expected.deleted_by)
    assert record_to_open(second.pk).deleted_by.username == "alice"
    assert record_to_open(uuid.uuid4()) is None


def test_an_uploads_rows_are_those_the_orm_writes(make_robot):
    """The insert and the seq update written once store what bulk_create and update() do:
    the same values read back for every field, created_at set, one statement each (the rows'
    INSERT one executemany, which Django's query log writes as "N times: INSERT ...")."""
    setup = make_robot("alice")
    with CaptureQueriesContext(connection) as queries:
        first = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1), setup.seal(2)])
    statements = [re.sub(r"^\d+ times: ", "", q["sql"]) for q in queries]
    writes = [sql.split()[0] for sql in statements if sql.startswith(("INSERT", "UPDATE"))]
    assert writes == ["UPDATE", "INSERT"]
    for record in first:
        assert (record._state.adding, record._state.db) == (False, "default")
        stored = Record.objects.get(pk=record.pk)
        assert fields_of(stored) == fields_of(record) | {"created_at": stored.created_at}
        assert stored.created_at is not None
        assert stored.status == Record.Status.PENDING
        assert stored.merkle_path == b""
        assert stored.anchor_root_id is None
    robot = Robot.objects.get(pk=setup.robot.pk)
    assert robot.last_seq == 2
    assert robot.last_upload_at is not None

    # The ORM's own writes of the same upload (another robot) hold the same values.
    twin = make_robot("bob")
    orm = Record.objects.bulk_create(
        [
            Record(**(fields_of(record) | {"id": uuid.uuid4(), "robot_id": twin.robot.pk}))
            for record in first
        ]
    )
    for ours, theirs in zip(first, orm, strict=True):
        mine = fields_of(Record.objects.get(pk=ours.pk))
        other = fields_of(Record.objects.get(pk=theirs.pk))
        for name in ("id", "robot_id", "created_at"):
            mine.pop(name), other.pop(name)
        assert mine == other


def test_the_seq_update_moves_only_above_the_last_seq_and_says_so(make_robot):
    setup = make_robot("alice")
    record_create_batch(robot=setup.robot, envelopes=[setup.seal(5)])
    assert _ROBOT_SEQ_MOVE.run((3, None), (setup.robot.pk, 3)) == 0  # 3 is not above 5
    assert Robot.objects.get(pk=setup.robot.pk).last_seq == 5
    assert _ROBOT_SEQ_MOVE.run((7, None), (setup.robot.pk, 6)) == 1
    robot = Robot.objects.get(pk=setup.robot.pk)
    assert (robot.last_seq, robot.last_upload_at) == (7, None)
    assert _ROBOT_SEQ_MOVE.run((9, None), (uuid.uuid4(), 8)) == 0  # no such robot


def test_a_model_with_an_automatic_key_gets_its_ids_from_the_insert_in_order(make_robot):
    setup = make_robot("alice")
    (record,) = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1)])
    (access_id,) = accesses_open(
        kind="page", viewer_id=setup.owner.pk, records=[record], credential="session", token_id=None
    ).values()
    outcomes = ["verified", "tampered", "no_access"]
    verdicts = [Verdict(record=record, access_id=access_id, outcome=o) for o in outcomes]
    with CaptureQueriesContext(connection) as queries:
        FixedInsert(Verdict).insert(verdicts)
    assert len(queries.captured_queries) == 1
    assert all(verdict.pk is not None and not verdict._state.adding for verdict in verdicts)
    read = [Verdict.objects.get(pk=verdict.pk) for verdict in verdicts]
    assert [verdict.outcome for verdict in read] == outcomes
    assert [verdict.created_at for verdict in read] == [verdict.created_at for verdict in verdicts]


def test_instances_made_are_the_orms_with_the_columns_not_read_deferred(make_robot):
    setup = make_robot("alice")
    record = record_create(robot=setup.robot, data=setup.seal(1))
    names = ["id", "owner_id", "topic", "digest"]
    (row,) = Record.objects.filter(pk=record.pk).values_list(*names)
    (made,) = instances_made(Record, names, [row], alias="default")
    expected = Record.objects.only(*names).get(pk=record.pk)
    assert made == expected
    assert {name: made.__dict__[name] for name in names} == {
        name: expected.__dict__[name] for name in names
    }
    assert made.get_deferred_fields() == expected.get_deferred_fields()
    assert (made._state.adding, made._state.db) == (False, "default")
    with CaptureQueriesContext(connection) as queries:
        assert made.seq == record.seq  # a column not read: read on first use, as only() does
    assert len(queries.captured_queries) == 1
    assert made.owner == setup.owner


def test_new_instances_made_are_those_the_constructor_makes(make_robot):
    setup = make_robot("alice")
    record = record_create(robot=setup.robot, data=setup.seal(1))
    (access,) = accesses_open(
        kind="view",
        viewer_id=setup.owner.pk,
        records=[record],
        credential="session",
        token_id=None,
    ).values()
    names = [field.attname for field in Verdict._meta.concrete_fields]
    given = {"record_id": record.pk, "access_id": access, "outcome": "verified"}
    row = [
        given.get(name, field.get_default())
        for name, field in zip(names, Verdict._meta.concrete_fields, strict=True)
    ]
    (made,) = instances_made(Verdict, names, [row], alias=None)
    expected = Verdict(**given)
    assert fields_of(made) == fields_of(expected)
    assert (made._state.adding, made._state.db) == (True, None)
    FixedInsert(Verdict).insert([made])
    assert fields_of(Verdict.objects.get(pk=made.pk)) == fields_of(made)


def test_a_model_with_init_receivers_is_made_by_its_constructor(make_robot):
    setup = make_robot("alice")
    record = record_create(robot=setup.robot, data=setup.seal(1))
    seen = []

    def receiver(sender, instance, **kwargs):
        seen.append(instance)

    post_init.connect(receiver, sender=Record)
    try:
        (made,) = instances_made(
            Record, ["id", "topic"], [(record.pk, record.topic)], alias="default"
        )
    finally:
        post_init.disconnect(receiver, sender=Record)
    assert seen == [made]
    assert (
        made.get_deferred_fields()
        == Record.objects.only("id", "topic").get(pk=record.pk).get_deferred_fields()
    )
