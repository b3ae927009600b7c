"""Robot pairing (issue 14): a robot's SM2 key pair, its owner's approval by code, its token
and the owner's key delivered once, encrypted to the robot; rotated keys reach paired robots;
envelopes spooled under a retired key still arrive when captured before the rotation.

Bad input answers a JSON 4xx and changes nothing; attacks leave a trace for the owner.
"""

import uuid
from datetime import UTC, datetime, timedelta

import pytest
from django.utils import timezone
from rest_framework.test import APIClient

from accounts.errors import (
    PairingAlreadyAnswered,
    PairingExpired,
    PairingNotFound,
)
from accounts.models import AccountEvent, Robot, RobotPairing
from accounts.selectors import (
    owner_key_bytes,
    owner_key_current,
    robot_by_token,
    robot_token_hash,
)
from accounts.services.keys import key_rotate
from accounts.services.pairing import (
    PAIRING_KEEP_EXPIRED,
    robot_pairing_answer,
    robot_pairings_purge,
)
from accounts.services.robots import robot_token_revoke
from sharing.services.uploads import KEY_ROTATION_GRACE
from smcrypto import envelope, provenance, sm2, sm4
from tests.api.conftest import Snapshot, b64, session_client, token_client

PAIRINGS = "/api/v1/robot-pairings/"
ROBOT_KEY = "/api/v1/robot-key/"
RECORDS = "/api/v1/records/"

pytestmark = pytest.mark.django_db


class Robotside:
    """What `python -m ros_agent pair` holds: its SM2 key pair and, once asked, its secret."""

    def __init__(self, name: str = "arm-3") -> None:
        self.name = name
        self.private_key, self.public_key = sm2.generate_keypair()
        self.api = APIClient()
        self.request: dict = {}

    def ask(self) -> dict:
        answer = self.api.post(
            PAIRINGS, {"name": self.name, "public_key": self.public_key}, format="json"
        )
        assert answer.status_code == 201, answer.json()
        self.request = answer.json()
        return self.request

    def collect(self, secret: str | None = None):
        return self.api.post(
            f"{PAIRINGS}{self.request['id']}/collect/",
            {"secret": secret or self.request["secret"]},
            format="json",
        )

    def decrypt(self, ciphertext: str) -> bytes:
        return sm2.decrypt(self.private_key, ciphertext)

    def seal(self, key: bytes, header: dict, body: bytes) -> bytes:
        """An envelope signed with the robot's pairing key, as its agent seals one."""
        signed = provenance.sign_header(self.private_key, self.public_key, header, body)
        return envelope.seal(key, signed, body)


@pytest.fixture
def owner(make_owner):
    return make_owner("alice")


def _approve(owner, code: str, **kwargs) -> RobotPairing:
    return robot_pairing_answer(owner=owner, code=code, approve=True, actor=owner.user, **kwargs)


def test_a_paired_robot_gets_its_token_and_its_owners_key_once_encrypted_to_it(owner):
    robot_side = Robotside()
    request = robot_side.ask()
    assert len(request["code"]) == 9
    assert request["code"][4] == "-"
    assert request["fingerprint"] == sm2.fingerprint(robot_side.public_key)
    pending = robot_side.collect()
    assert (pending.status_code, pending.json()["state"]) == (202, "pending")
    assert not Robot.objects.exists()

    # The owner types the code as people do: lower case, without the dash.
    pairing = _approve(owner, request["code"].replace("-", "").lower())
    delivered = robot_side.collect()
    assert delivered.status_code == 200
    body = delivered.json()
    assert (body["state"], body["owner"], body["name"], body["mode"]) == (
        "approved",
        "alice",
        "arm-3",
        "C1C3C2",
    )
    token = robot_side.decrypt(body["token_sm2"]).decode()
    key = robot_side.decrypt(body["key_sm2"])
    assert key == owner_key_bytes(owner_key_current(owner))
    assert body["key_id"] == envelope.key_id(key).hex()
    robot = robot_by_token(token)
    assert robot is not None
    assert str(robot.pk) == body["robot"]
    assert robot.public_key == sm2.public_key_normalize(robot_side.public_key)
    assert body["topics"] == robot.topics

    # Once: a second collection gets nothing, and nothing secret stays in the clear.
    again = robot_side.collect()
    assert (again.status_code, again.json()["error"]) == (409, "pairing_already_collected")
    assert "token_sm2" not in again.json()
    pairing.refresh_from_db()
    assert (pairing.state, pairing.token_sm2) == (RobotPairing.State.DELIVERED, "")
    assert pairing.secret_hash == robot_token_hash(request["secret"])
    assert AccountEvent.objects.filter(owner=owner, kind=AccountEvent.Kind.ROBOT_PAIRED).exists()

    # The token uploads, under the key the robot received.
    header = {
        "owner": "alice",
        "robot": body["robot"],
        "topic": "/chatter",
        "type": "std_msgs/String",
        "seq": 1,
        "time": datetime.now(UTC).isoformat().replace("+00:00", "Z"),
    }
    upload = token_client(token).post(
        RECORDS, {"envelope": b64(robot_side.seal(key, header, b"{}"))}, format="json"
    )
    assert upload.status_code == 201, upload.json()
    assert upload["AuthROS-Key-Id"] == body["key_id"]


def test_someone_without_the_robots_secret_gets_nothing_and_the_owner_is_told(owner, client):
    robot_side = Robotside()
    request = robot_side.ask()
    _approve(owner, request["code"])
    stolen = robot_side.collect(secret="guessed-" + request["secret"][8:])
    assert (stolen.status_code, stolen.json()["error"]) == (403, "pairing_secret_mismatch")
    assert "token_sm2" not in stolen.json()
    assert AccountEvent.objects.filter(
        owner=owner, kind=AccountEvent.Kind.PAIRING_SECRET_MISMATCH
    ).exists()
    client.force_login(owner.user)
    security = client.get("/account/security/").content.decode()
    entry = security.split('data-kind="pairing_secret_mismatch"', 1)[1].split("</li>", 1)[0]
    assert "alarm" in entry
    # The robot itself still collects what is its own.
    assert robot_side.collect().status_code == 200


def test_a_refused_robot_gets_nothing(owner):
    robot_side = Robotside()
    request = robot_side.ask()
    robot_pairing_answer(owner=owner, code=request["code"], approve=False, actor=owner.user)
    refused = robot_side.collect()
    assert (refused.status_code, refused.json()["error"]) == (403, "pairing_refused")
    assert not Robot.objects.exists()
    with pytest.raises(PairingAlreadyAnswered):
        _approve(owner, request["code"])
    assert not Robot.objects.exists()


def test_a_request_is_answered_once(owner, make_owner):
    robot_side = Robotside()
    request = robot_side.ask()
    _approve(owner, request["code"])
    with pytest.raises(PairingAlreadyAnswered):
        _approve(owner, request["code"])
    # Another owner cannot take it over either: to it, the code is unknown.
    with pytest.raises(PairingNotFound):
        _approve(make_owner("mallory"), request["code"])
    assert Robot.objects.count() == 1


def test_an_expired_request_can_neither_be_approved_nor_collected(owner):
    robot_side = Robotside()
    request = robot_side.ask()
    RobotPairing.objects.update(expires_at=timezone.now() - timedelta(seconds=1))
    with pytest.raises(PairingExpired):
        _approve(owner, request["code"])
    expired = robot_side.collect()
    assert (expired.status_code, expired.json()["error"]) == (409, "pairing_expired")
    assert not Robot.objects.exists()


def test_unanswered_requests_are_purged_a_day_after_they_expired(owner):
    stale, fresh, answered = Robotside(), Robotside(), Robotside()
    for robot_side in (stale, fresh, answered):
        robot_side.ask()
    robot_pairing_answer(owner=owner, code=answered.request["code"], approve=False, actor=None)
    long_ago = timezone.now() - PAIRING_KEEP_EXPIRED - timedelta(minutes=1)
    RobotPairing.objects.exclude(pk=fresh.request["id"]).update(expires_at=long_ago)
    assert robot_pairings_purge() == 1
    assert set(RobotPairing.objects.values_list("pk", flat=True)) == {
        uuid.UUID(fresh.request["id"]),
        uuid.UUID(answered.request["id"]),
    }


def test_a_wrong_code_finds_nothing(owner):
    Robotside().ask()
    with pytest.raises(PairingNotFound):
        _approve(owner, "ZZZZ-ZZZZ")
    assert not Robot.objects.exists()


@pytest.mark.parametrize(
    "body",
    [
        {"name": "arm", "public_key": "04" + "11" * 64},  # well formed, not on the curve
        {"name": "arm", "public_key": "04" + "zz" * 64},
        {"name": "arm", "public_key": "04abcd"},
        {"name": "", "public_key": sm2.generate_keypair()[1]},
        {"name": "a" * 101, "public_key": sm2.generate_keypair()[1]},
        {"name": 5, "public_key": sm2.generate_keypair()[1]},
        {"name": "arm\x00", "public_key": sm2.generate_keypair()[1]},
        {"public_key": sm2.generate_keypair()[1]},
        ["not", "a", "mapping"],
    ],
)
def test_bad_pairing_requests_are_refused_and_store_nothing(db, body):
    answer = APIClient().post(PAIRINGS, body, format="json")
    assert answer.status_code == 400
    assert answer.json()["error"] in ("invalid_request", "invalid_pairing_request")
    assert not RobotPairing.objects.exists()


@pytest.mark.parametrize(
    "name",
    [
        "arm\u202egnp.exe",  # right-to-left override
        "arm\u202a",
        "\u2066arm\u2069",  # isolates
        "arm\x1b[2J",  # ESC, a terminal escape
        "arm\r\nApproved: yes",
        "arm\nsecond line",
        "arm\u200bx",  # zero-width space
        "arm\u2028x",  # line separator
        "arm\x7f",
    ],
)
def test_pairing_names_are_printable_text(db, name):
    answer = APIClient().post(
        PAIRINGS, {"name": name, "public_key": sm2.generate_keypair()[1]}, format="json"
    )
    assert answer.status_code == 400
    assert answer.json()["error"] == "invalid_pairing_request"
    assert "printable text" in answer.json()["detail"]
    assert not RobotPairing.objects.exists()


def test_a_name_in_any_script_is_taken(db):
    answer = APIClient().post(
        PAIRINGS,
        {"name": "Bras robotisé 3 — 机器人 ✓", "public_key": sm2.generate_keypair()[1]},
        format="json",
    )
    assert answer.status_code == 201
    assert RobotPairing.objects.get().name == "Bras robotisé 3 — 机器人 ✓"


def test_collecting_an_unknown_request_is_a_json_404(db):
    answer = APIClient().post(
        f"{PAIRINGS}{uuid.uuid4()}/collect/", {"secret": "x" * 43}, format="json"
    )
    assert (answer.status_code, answer.json()["error"]) == (404, "pairing_not_found")
    malformed = APIClient().post(
        f"{PAIRINGS}not-a-uuid/collect/", {"secret": "x" * 43}, format="json"
    )
    assert (malformed.status_code, malformed.json()["error"]) == (404, "pairing_not_found")


def test_pairing_endpoints_are_rate_limited_per_address(db, settings):
    rates = settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"]
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {**rates, "pairing": "3/minute"},
    }
    robot_side = Robotside()
    robot_side.ask()
    assert robot_side.collect().status_code == 202
    assert robot_side.collect().status_code == 202
    limited = robot_side.collect()
    assert (limited.status_code, limited.json()["error"]) == (429, "rate_limited")
    assert "Retry-After" in limited


# --- key delivery after pairing ------------------------------------------------------------


def _paired(owner) -> tuple[Robotside, str, Robot]:
    robot_side = Robotside(name=f"arm-{uuid.uuid4().hex[:4]}")
    request = robot_side.ask()
    _approve(owner, request["code"])
    body = robot_side.collect().json()
    token = robot_side.decrypt(body["token_sm2"]).decode()
    return robot_side, token, Robot.objects.get(pk=body["robot"])


def test_a_rotated_key_reaches_a_paired_robot_encrypted_to_it(
    owner, django_capture_on_commit_callbacks
):
    robot_side, token, _robot = _paired(owner)
    first = token_client(token).get(ROBOT_KEY)
    assert first.status_code == 200
    assert robot_side.decrypt(first.json()["key_sm2"]) == owner_key_bytes(owner_key_current(owner))
    with django_capture_on_commit_callbacks(execute=True):
        new_key = key_rotate(owner=owner, sm4_key=sm4.generate_key())
    after = token_client(token).get(ROBOT_KEY)
    assert after.json()["key_id"] == new_key.key_id != first.json()["key_id"]
    assert robot_side.decrypt(after.json()["key_sm2"]) == owner_key_bytes(new_key)
    # Someone else's SM2 key cannot read it.
    with pytest.raises(Exception, match="C3 check failed"):
        sm2.decrypt(sm2.generate_keypair()[0], after.json()["key_sm2"])


def test_unpairing_stops_key_delivery(owner):
    _robot_side, token, robot = _paired(owner)
    robot_token_revoke(robot=robot, actor=owner.user)
    refused = token_client(token).get(ROBOT_KEY)
    assert (refused.status_code, refused.json()["error"]) == (401, "not_authenticated")


def test_only_paired_robots_fetch_the_key(make_robot):
    by_hand = make_robot()
    refused = token_client(by_hand.token).get(ROBOT_KEY)
    assert (refused.status_code, refused.json()["error"]) == (409, "robot_not_paired")
    as_owner = session_client(by_hand.owner).get(ROBOT_KEY)
    assert (as_owner.status_code, as_owner.json()["error"]) == (403, "permission_denied")
    assert APIClient().get(ROBOT_KEY).status_code == 401


def test_answers_to_a_paired_robots_uploads_name_the_current_key_even_refusals(
    owner, django_capture_on_commit_callbacks, make_robot
):
    _robot_side, token, robot = _paired(owner)
    with django_capture_on_commit_callbacks(execute=True):
        new_key = key_rotate(owner=owner, sm4_key=sm4.generate_key())
    header = {
        "owner": owner.username,
        "robot": str(robot.pk),
        "topic": "/chatter",
        "type": "std_msgs/String",
        "seq": 1,
        "time": _iso(datetime.now(UTC)),
    }
    stranger = token_client(token).post(
        RECORDS,
        {"envelope": b64(envelope.seal(sm4.generate_key(), header, b"{}"))},
        format="json",
    )
    assert (stranger.status_code, stranger.json()["error"]) == (403, "unknown_key")
    assert stranger["AuthROS-Key-Id"] == new_key.key_id
    # A robot set up by hand cannot fetch a key: its answers do not name one.
    by_hand = make_robot()
    answer = token_client(by_hand.token).post(
        RECORDS, {"envelope": b64(by_hand.seal(1))}, format="json"
    )
    assert answer.status_code == 201
    assert "AuthROS-Key-Id" not in answer


def _header(robot, seq: int, time: datetime | None = None) -> dict:
    return {
        "owner": robot.owner.username,
        "robot": str(robot.robot.id),
        "topic": "/robot/odom",
        "type": "nav_msgs/Odometry",
        "seq": seq,
        "time": (time or datetime.now(UTC)).isoformat().replace("+00:00", "Z"),
    }


def test_envelopes_captured_before_a_rotation_are_accepted_under_the_old_key_for_good(
    robot, robot_api, upload, django_capture_on_commit_callbacks, settings
):
    """A robot offline for a day with a full spool: what it captured before the rotation
    arrives; what it sealed under the old key after the rotation (skew allowed) is refused,
    for its agent to re-seal under the new key."""
    skew = timedelta(seconds=settings.KEY_ROTATION_CLOCK_SKEW)
    with django_capture_on_commit_callbacks(execute=True):
        key_rotate(owner=robot.owner, sm4_key=sm4.generate_key())
    retired_at = timezone.now() - KEY_ROTATION_GRACE - timedelta(days=1)
    robot.owner.keys.filter(key_id=envelope.key_id(robot.key).hex()).update(retired_at=retired_at)
    before_rotation = robot.seal(1, time=_iso(retired_at - timedelta(hours=2)))
    within_skew = robot.seal(2, time=_iso(retired_at + skew / 2))
    answer = upload(robot_api, before_rotation, within_skew, batch=True)
    assert answer.status_code == 201, answer.json()

    before = Snapshot()
    after_rotation = robot.seal(3, time=_iso(retired_at + skew * 2))
    refused = upload(robot_api, after_rotation)
    assert (refused.status_code, refused.json()["error"]) == (403, "unknown_key")
    assert before.unchanged()


def _iso(moment: datetime) -> str:
    return moment.astimezone(UTC).isoformat().replace("+00:00", "Z")


# --- the robots page ------------------------------------------------------------------------


def test_the_owner_pairs_a_robot_on_the_robots_page(owner, client):
    robot_side = Robotside(name="lidar-cart")
    request = robot_side.ask()
    client.force_login(owner.user)

    wrong = client.get("/robots/pair/", {"code": "0000-0000"})
    assert wrong.status_code == 404
    assert b"No robot waits for an answer with this code" in wrong.content

    found = client.get("/robots/pair/", {"code": request["code"]})
    assert found.status_code == 200
    page = found.content.decode()
    assert request["fingerprint"] in page
    assert "lidar-cart" in page
    assert request["code"] in page

    approved = client.post(
        "/robots/pair/", {"code": request["code"], "name": "", "decision": "approve"}
    )
    assert approved.status_code == 302
    assert Robot.objects.get(owner=owner).name == "lidar-cart"
    again = client.post(
        "/robots/pair/", {"code": request["code"], "name": "", "decision": "approve"}
    )
    assert again.status_code == 409
    assert Robot.objects.count() == 1
    assert robot_side.collect().status_code == 200
    robots_page = client.get("/robots/").content.decode()
    assert "Unpair" in robots_page
    assert "fetches rotated keys" in robots_page
    # A paired robot wrote its own config: no hand-made one (with a key file) is offered.
    paired = Robot.objects.get(owner=owner)
    assert f"/robots/{paired.pk}/agent.yaml" not in robots_page


def test_a_paired_robot_gets_no_grace_hour_its_agent_reseals(
    owner, django_capture_on_commit_callbacks, settings
):
    """Robots with a key file set by hand may send under the old key for an hour after a
    rotation; a paired robot fetches the new key, so an envelope it captured after the
    rotation under the old key is refused (its agent re-seals it)."""
    _robot_side, token, robot = _paired(owner)
    old_key = owner_key_bytes(owner_key_current(owner))
    with django_capture_on_commit_callbacks(execute=True):
        key_rotate(owner=owner, sm4_key=sm4.generate_key())
    retired_at = owner.keys.get(is_current=False).retired_at
    late = retired_at + timedelta(seconds=settings.KEY_ROTATION_CLOCK_SKEW * 2)
    header = {
        "owner": owner.username,
        "robot": str(robot.pk),
        "topic": "/chatter",
        "type": "std_msgs/String",
        "seq": 1,
        "time": _iso(late),
    }
    answer = token_client(token).post(
        RECORDS, {"envelope": b64(envelope.seal(old_key, header, b"{}"))}, format="json"
    )
    assert (answer.status_code, answer.json()["error"]) == (403, "unknown_key")
