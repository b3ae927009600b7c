"""A small world of views for the access log tests, made straight in the database (no chain:
the log only reads accesses and their verdicts): alice shares with bob; carol shares with bob too.

Views, oldest first (minutes after NOON; `old` a day before, from before credentials were
recorded):

    old  alice views her /odom record          (not recorded)  verified
    a1   alice views her /odom record          session         verified    0
    a2   bob views alice's /camera record      token           verified    1
    a3   bob views alice's /odom record        session         TAMPERED    2
    a4   an operator checks alice's /camera    operator        verified    3
    c1   bob views carol's record              session         verified    4
    c2   carol views her own record            session         verified    5
"""

import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta

from django.contrib.auth import get_user_model

from accounts.models import Owner, OwnerToken, Robot
from accounts.services.api_tokens import owner_token_create
from accounts.services.owners import owner_create
from accounts.services.robots import robot_create
from sharing.models import Access, Credential, Grant, Record, Verdict
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
# Names a spreadsheet would run as formulas, if the CSV let them through.
FORMULA_ROBOT = '=HYPERLINK("http://evil","x")'
FORMULA_TOPIC = "@SUM(1+1)"
FORMULA_TOKEN = "+cmd|' /C calc'!A0"
CAROL_TOPIC = "/carol/private"


def at(minutes: float) -> datetime:
    return NOON + timedelta(minutes=minutes)


@dataclass
class World:
    alice: Owner
    bob: Owner
    carol: Owner
    arm: Robot  # alice's
    rover: Robot  # alice's, named like a formula
    token: OwnerToken  # bob's
    records: dict[str, Record] = field(default_factory=dict)
    views: dict[str, Verdict] = field(default_factory=dict)

    def access_ids(self, *names: str) -> list[int]:
        return [self.views[name].access_id for name in names]


def _owner(name: str, *, signed_up: bool) -> Owner:
    return owner_create(
        username=name, password=TEST_PASSWORD, sm4_key=sm4.generate_key(), self_signup=signed_up
    )


def stored_record(robot: Robot, seq: int, topic: str, data_type: str) -> Record:
    return Record.objects.create(
        owner=robot.owner,
        robot=robot,
        topic=topic,
        data_type=data_type,
        seq=seq,
        captured_at=at(-60 + seq),
        key_id="00" * 8,
        digest=uuid.uuid4().hex * 2,
        size=100,
        storage_name=f"x/{uuid.uuid4().hex}",
        status=Record.Status.ANCHORED,
    )


def view(
    record: Record,
    viewer: Owner,
    minutes: float,
    *,
    outcome: str = Verdict.Outcome.VERIFIED,
    credential: str = Credential.SESSION,
    token: OwnerToken | None = None,
    checked_by: object = None,
) -> Verdict:
    """A view of one record as the worker writes it, at NOON + minutes: its access and its
    verdict."""
    access = Access.objects.create(
        kind=Access.Kind.CHECK if checked_by else Access.Kind.VIEW,
        viewer=viewer,
        record_owner_id=record.owner_id,
        credential=credential,
        token=token,
        checked_by=checked_by,
        count=1,
        record=record,
        robot_id=record.robot_id,
        topic=record.topic,
    )
    Access.objects.filter(pk=access.pk).update(created_at=at(minutes))
    verdict = Verdict.objects.create(access=access, record=record, outcome=outcome, block_number=7)
    Verdict.objects.filter(pk=verdict.pk).update(created_at=at(minutes))
    verdict.refresh_from_db()
    return verdict


def plot(records: list[Record], viewer: Owner, minutes: float) -> Access:
    """A plot of `viewer`'s over the records (all of one owner), at NOON + minutes: one access
    of kind plot naming how many, a verified verdict per record under it."""
    owner_id = records[0].owner_id
    access = Access.objects.create(
        kind=Access.Kind.PLOT,
        viewer=viewer,
        record_owner_id=owner_id,
        credential=Credential.SESSION,
        count=len(records),
        topic=records[0].topic,
        robot_id=records[0].robot_id,
    )
    Access.objects.filter(pk=access.pk).update(created_at=at(minutes))
    Verdict.objects.bulk_create(
        Verdict(access=access, record=record, outcome=Verdict.Outcome.VERIFIED, block_number=7)
        for record in records
    )
    access.refresh_from_db()
    return access


def access_log_world(*, signed_up: bool = False) -> World:
    """The world above. `signed_up`: the owners signed up themselves, and with
    SIGNUP_APPROVAL they await an operator, so that nothing goes to the chain even where
    on-commit work runs (a live server's test)."""
    alice, bob, carol = (_owner(name, signed_up=signed_up) for name in ("alice", "bob", "carol"))
    arm, _ = robot_create(owner=alice, name="arm")
    rover, _ = robot_create(owner=alice, name=FORMULA_ROBOT)
    carols, _ = robot_create(owner=carol, name="carols-robot")
    token, _key = owner_token_create(
        owner=bob, name=FORMULA_TOKEN, scopes=["read"], expires_in=timedelta(days=30)
    )
    for owner in (alice, carol):
        Grant.objects.create(owner=owner, grantee=bob, status=Grant.Status.ACTIVE)
    operator = get_user_model().objects.create_user(
        username="operator", password=TEST_PASSWORD, is_staff=True
    )
    world = World(alice, bob, carol, arm, rover, token)
    odom = stored_record(arm, 1, "/odom", "nav_msgs/Odometry")
    camera = stored_record(rover, 2, FORMULA_TOPIC, "sensor_msgs/Image")
    private = stored_record(carols, 1, CAROL_TOPIC, "std_msgs/String")
    world.records = {"odom": odom, "camera": camera, "private": private}
    world.views = {
        "old": view(odom, alice, -24 * 60, credential=Credential.UNKNOWN),
        "a1": view(odom, alice, 0),
        "a2": view(camera, bob, 1, credential=Credential.TOKEN, token=token),
        "a3": view(odom, bob, 2, outcome=Verdict.Outcome.TAMPERED),
        "a4": view(camera, alice, 3, credential=Credential.OPERATOR, checked_by=operator),
        "c1": view(private, bob, 4),
        "c2": view(private, carol, 5),
    }
    return world
