"""Reading records: the list, one record's status, and its integrity-checked content."""

import base64
import json
import uuid
from datetime import UTC, datetime, timedelta

import pytest
from django.contrib.auth import get_user_model

from sharing.cache import envelope_cache_evict
from sharing.models import Grant, Record, Verdict
from sharing.services.grants import grant_create, grant_revoke
from sharing.storage import envelope_storage
from smcrypto import envelope, sm3
from smcrypto.errors import WrongKey
from stack.anvil import free_port
from tests.api.conftest import RECORDS, session_client, token_client
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db


def _at(minutes: int) -> str:
    moment = datetime(2026, 3, 1, 12, 0, tzinfo=UTC) + timedelta(minutes=minutes)
    return moment.isoformat().replace("+00:00", "Z")


def _sealed(setup, seq: int, *, topic: str, data_type: str, minutes: int, body: dict) -> bytes:
    header = {
        "owner": setup.owner.username,
        "robot": str(setup.robot.id),
        "topic": topic,
        "type": data_type,
        "seq": seq,
        "time": _at(minutes),
    }
    return envelope.seal(setup.key, header, json.dumps(body).encode())


@pytest.fixture
def fleet(robot, robot_api, upload):
    """Four records of one robot: odometry and strings, a minute apart, all anchored."""
    envelopes = [
        _sealed(robot, 1, topic="/odom", data_type="nav_msgs/Odometry", minutes=0, body={"n": 1}),
        _sealed(robot, 2, topic="/chatter", data_type="std_msgs/String", minutes=1, body={"n": 2}),
        _sealed(robot, 3, topic="/odom", data_type="nav_msgs/Odometry", minutes=2, body={"n": 3}),
        _sealed(robot, 4, topic="/chatter", data_type="std_msgs/String", minutes=3, body={"n": 4}),
    ]
    assert upload(robot_api, *envelopes).status_code == 201
    return envelopes


def _seqs(answer) -> list[int]:
    assert answer.status_code == 200, answer.content
    return [record["seq"] for record in answer.json()["results"]]


def test_the_list_is_newest_first_and_filters(robot_api, fleet):
    assert _seqs(robot_api.get(RECORDS)) == [4, 3, 2, 1]
    assert _seqs(robot_api.get(RECORDS, {"topic": "/odom"})) == [3, 1]
    assert _seqs(robot_api.get(RECORDS, {"type": "std_msgs/String"})) == [4, 2]
    assert _seqs(robot_api.get(RECORDS, {"status": "anchored"})) == [4, 3, 2, 1]
    assert _seqs(robot_api.get(RECORDS, {"status": "pending"})) == []
    assert _seqs(robot_api.get(RECORDS, {"since": _at(1), "until": _at(3)})) == [3, 2]
    assert _seqs(robot_api.get(RECORDS, {"since": "2026-03-01T13:02:00+01:00"})) == [4, 3]
    assert _seqs(robot_api.get(RECORDS, {"topic": "/nowhere"})) == []


def test_the_list_is_paginated(robot_api, fleet):
    first = robot_api.get(RECORDS, {"limit": 3})
    assert _seqs(first) == [4, 3, 2]
    assert first.json()["count"] == 4
    assert first.json()["previous"] is None
    second = robot_api.get(first.json()["next"])
    assert _seqs(second) == [1]
    assert second.json()["next"] is None
    assert _seqs(robot_api.get(RECORDS, {"offset": 100})) == []


def test_the_next_page_stays_while_the_robot_uploads(robot, robot_api, upload, fleet):
    """The `next` link is a cursor of capture time (issue 48), not an offset: records uploaded
    between two pages neither push one onto the next page twice nor into it."""
    first = robot_api.get(RECORDS, {"limit": 2})
    assert _seqs(first) == [4, 3]
    assert "after=" in first.json()["next"]
    assert "offset=" not in first.json()["next"]
    newer = [
        _sealed(robot, seq, topic="/odom", data_type="nav_msgs/Odometry", minutes=seq, body={})
        for seq in (5, 6)
    ]
    assert upload(robot_api, *newer).status_code == 201
    second = robot_api.get(first.json()["next"])
    assert _seqs(second) == [2, 1]
    assert second.json()["next"] is None
    # Offsets still page as before, for the clients that send them.
    assert _seqs(robot_api.get(RECORDS, {"limit": 2, "offset": 2})) == [4, 3]


@pytest.mark.parametrize(
    "cursor",
    [
        "yesterday",
        "2026-03-01T12:00:00.000000Z_xyz",
        "_",
        "2026-03-01T12:00:00Z_" + "0" * 32,
        "é" * 100,
    ],
)
def test_a_bad_cursor_gets_400(robot_api, cursor):
    answer = robot_api.get(RECORDS, {"after": cursor})
    assert answer.status_code == 400, answer.content
    assert answer.json()["error"] == "invalid_request"


def test_one_record_in_the_list_says_everything_about_it(robot, robot_api, fleet):
    listed = robot_api.get(RECORDS, {"limit": 1}).json()["results"][0]
    record = Record.objects.get(seq=4)
    assert listed == {
        "id": str(record.id),
        "owner": robot.owner.username,
        "owner_address": robot.owner.eoa_address,
        "robot": str(robot.robot.id),
        "robot_name": robot.robot.name,
        "topic": "/chatter",
        "type": "std_msgs/String",
        "seq": 4,
        "captured_at": _at(3),
        "size": len(fleet[3]),
        "digest": sm3.sm3_hex(fleet[3]),
        "key_id": envelope.key_id(robot.key).hex(),
        "signer": None,  # a robot added by hand signs nothing
        "status": "anchored",
        "tx_hash": record.tx_hash,
        "block_number": record.block_number,
        "anchored_at": listed["anchored_at"],
        "failure_reason": None,
        "tampered_at": None,
        "created_at": listed["created_at"],
        "deleted_at": None,
        "deleted_by": None,
        "deletion_reason": None,
    }
    assert listed["anchored_at"] is not None


def test_bad_filters_get_400(robot_api):
    queries = [
        {"status": "lost"},
        {"since": "yesterday"},
        {"until": "2026-13-01T00:00:00Z"},
        {"since": "9999-12-31T23:59:59-12:00"},
        {"robot": "not-a-uuid"},
        {"topic": "x" * 300},
        {"topic": "a\x00b"},
        {"limit": 0},
        {"limit": 501},
        {"limit": "ten"},
        {"offset": -1},
        {"offset": 10**30},
    ]
    for query in queries:
        answer = robot_api.get(RECORDS, query)
        assert answer.status_code == 400, (query, answer.content)
        assert answer.json()["error"] == "invalid_request", query
        assert answer.json()["fields"], query


def test_detail_shows_pending_anchored_and_failed(robot, robot_api, upload):
    pending = robot_api.post(RECORDS, {"envelope": _b64(robot.seal(1))}, format="json").json()
    detail = robot_api.get(f"{RECORDS}{pending['id']}/").json()
    assert (detail["status"], detail["tx_hash"], detail["block_number"]) == ("pending", None, None)

    anchored = upload(robot_api, robot.seal(2)).json()
    detail = robot_api.get(f"{RECORDS}{anchored['id']}/").json()
    assert detail["status"] == "anchored"
    assert detail["tx_hash"] == Record.objects.get(pk=anchored["id"]).tx_hash
    assert detail["block_number"] > 0

    Record.objects.filter(pk=pending["id"]).update(
        status=Record.Status.FAILED, failure_reason="chain holds another digest"
    )
    detail = robot_api.get(f"{RECORDS}{pending['id']}/").json()
    assert (detail["status"], detail["failure_reason"]) == ("failed", "chain holds another digest")


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def test_unknown_or_malformed_record_ids_get_a_json_404(robot, owner_api):
    reader = owner_api(robot.owner)
    for record_id in (str(uuid.uuid4()), "not-a-uuid", "%00", "1" * 300, "0" * 33, "%C3%A9"):
        for path in (f"{RECORDS}{record_id}/", f"{RECORDS}{record_id}/content/"):
            answer = reader.get(path)
            assert answer.status_code == 404, path
            assert answer.json()["error"] == "not_found", path
    assert not Verdict.objects.exists()


def test_an_owner_reads_its_content_checked_and_sealed_under_its_key(robot, owner_api, fleet):
    record = Record.objects.get(seq=2)
    answer = owner_api(robot.owner, scopes=("read",)).get(f"{RECORDS}{record.id}/content/")
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert body["verified"] is True
    assert body["digest"] == record.digest == sm3.sm3_hex(fleet[1])
    assert body["id"] == str(record.id)
    header, plaintext = envelope.open(robot.key, base64.b64decode(body["envelope"]))
    assert header == envelope.read_header(fleet[1]).header
    assert json.loads(plaintext) == {"n": 2}
    assert Verdict.objects.get().outcome == Verdict.Outcome.VERIFIED


def test_a_browser_session_reads_the_same(robot, fleet):
    browser = session_client(robot.owner)
    assert _seqs(browser.get(RECORDS)) == [4, 3, 2, 1]
    record = Record.objects.get(seq=1)
    assert browser.get(f"{RECORDS}{record.id}/").status_code == 200
    content = browser.get(f"{RECORDS}{record.id}/content/")
    assert content.status_code == 200
    _, plaintext = envelope.open(robot.key, base64.b64decode(content.json()["envelope"]))
    assert json.loads(plaintext) == {"n": 1}


def test_a_grantee_sees_and_reads_shared_records_under_its_own_key(
    robot, fleet, make_robot, owner_api, django_capture_on_commit_callbacks
):
    reader = make_robot()
    reader_api = owner_api(reader.owner, scopes=("read",))
    record = Record.objects.get(seq=3)
    content = f"{RECORDS}{record.id}/content/"

    assert _seqs(reader_api.get(RECORDS)) == []
    assert reader_api.get(f"{RECORDS}{record.id}/").status_code == 404
    refused = reader_api.get(content)
    assert refused.status_code == 404
    assert refused.json()["error"] == "not_found"

    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=robot.owner, grantee=reader.owner)
    assert _seqs(reader_api.get(RECORDS)) == [4, 3, 2, 1]
    assert _seqs(reader_api.get(RECORDS, {"owner": robot.owner.username})) == [4, 3, 2, 1]
    assert _seqs(reader_api.get(RECORDS, {"owner": reader.owner.username})) == []
    assert reader_api.get(f"{RECORDS}{record.id}/").status_code == 200
    answer = reader_api.get(content)
    assert answer.status_code == 200
    resealed = base64.b64decode(answer.json()["envelope"])
    with pytest.raises(WrongKey):
        envelope.open(robot.key, resealed)  # not under the owner's key ...
    _, plaintext = envelope.open(reader.key, resealed)  # ... under the reader's own
    assert json.loads(plaintext) == {"n": 3}

    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=robot.owner, grantee=reader.owner)
    assert Grant.objects.get().status == Grant.Status.REVOKED
    assert _seqs(reader_api.get(RECORDS)) == []
    assert reader_api.get(content).status_code == 404


def test_changed_stored_data_is_refused_with_409(robot, robot_api, owner_api, fleet):
    record = Record.objects.get(seq=1)
    with envelope_storage().open(record.storage_name, "rb") as handle:
        data = bytearray(handle.read())
    data[-1] ^= 1
    path = envelope_storage().path(record.storage_name)
    with open(path, "wb") as handle:
        handle.write(bytes(data))
    envelope_cache_evict(record.id)
    answer = owner_api(robot.owner).get(f"{RECORDS}{record.id}/content/")
    assert answer.status_code == 409
    assert answer.json()["error"] == "integrity_check_failed"
    record.refresh_from_db()
    assert record.tampered_at is not None
    assert robot_api.get(f"{RECORDS}{record.id}/").json()["tampered_at"] is not None


def test_content_before_anchoring_is_409_not_anchored_yet(robot, robot_api, owner_api):
    uploaded = robot_api.post(RECORDS, {"envelope": _b64(robot.seal(1))}, format="json").json()
    answer = owner_api(robot.owner).get(f"{RECORDS}{uploaded['id']}/content/")
    assert answer.status_code == 409
    assert answer.json()["error"] == "not_anchored_yet"


def test_content_when_the_check_cannot_run_is_503_and_shows_nothing(
    robot, owner_api, fleet, settings
):
    reader = owner_api(robot.owner)
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    record = Record.objects.get(seq=1)
    answer = reader.get(f"{RECORDS}{record.id}/content/")
    assert answer.status_code == 503
    assert answer.json()["error"] == "verification_unavailable"
    assert "envelope" not in answer.json()
    assert int(answer["Retry-After"]) > 0


def test_a_user_who_is_no_owner_is_refused(client):
    staff = get_user_model().objects.create_user("operator", password="x", is_staff=True)
    client.force_login(staff)
    for path in (RECORDS, f"{RECORDS}{uuid.uuid4()}/", "/api/v1/grants/"):
        answer = client.get(path)
        assert answer.status_code == 403, path
        assert answer.json()["error"] == "permission_denied"


def test_nobody_reads_without_credentials(robot, fleet, client):
    record = Record.objects.get(seq=1)
    for path in (RECORDS, f"{RECORDS}{record.id}/", f"{RECORDS}{record.id}/content/"):
        answer = client.get(path)
        assert answer.status_code == 401, path
        assert answer.json()["error"] == "not_authenticated"


def test_another_owners_records_are_invisible(robot, fleet, make_robot, owner_api):
    stranger = make_robot()
    stranger_api = token_client(stranger.token)
    record = Record.objects.get(seq=1)
    for reader in (stranger_api, owner_api(stranger.owner)):
        assert _seqs(reader.get(RECORDS)) == []
        assert _seqs(reader.get(RECORDS, {"owner": robot.owner.username})) == []
        assert reader.get(f"{RECORDS}{record.id}/").status_code == 404
    # An envelope for someone else's robot cannot be planted through the stranger either.
    planted = seal_for(robot.robot, robot.key, seq=99)
    answer = stranger_api.post(RECORDS, {"envelope": _b64(planted)}, format="json")
    assert answer.status_code == 403


def test_a_post_to_no_endpoint_with_a_session_is_a_json_404(robot):
    """Not Django's HTML CSRF page: the API answers in its own shape even there."""
    browser = session_client(robot.owner, enforce_csrf=True)
    answer = browser.post("/api/v1/no-such-endpoint/", {"x": 1}, format="json")
    assert answer.status_code == 404
    assert answer.json()["error"] == "not_found"
