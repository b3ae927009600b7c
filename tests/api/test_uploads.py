"""`POST /api/v1/records/`: what a robot may upload, and every refusal, which changes nothing."""

import json
from datetime import timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from accounts import authentication
from accounts.services.keys import key_rotate
from accounts.services.robots import robot_create, robot_token_revoke
from chainworker import services as chain_services
from core.redis_client import get_redis, redis_key
from sharing.models import Record, SecurityEvent
from sharing.services.uploads import KEY_ROTATION_GRACE
from smcrypto import envelope, sm3, sm4
from tests.api.conftest import RECORDS, Snapshot, b64, session_client, token_client
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db


def test_one_envelope_is_stored_and_anchored(robot, robot_api, upload):
    data = robot.seal(1, plaintext=b'{"K": {"x": 1}}')
    answer = upload(robot_api, data)
    assert answer.status_code == 201
    body = answer.json()
    assert set(body) == {"id", "digest", "status", "seq"}
    assert body["digest"] == sm3.sm3_hex(data)
    assert body["seq"] == 1
    record = Record.objects.get(pk=body["id"])
    assert (record.robot_id, record.owner_id, record.digest) == (
        robot.robot.pk,
        robot.owner.pk,
        body["digest"],
    )
    detail = robot_api.get(f"{RECORDS}{body['id']}/").json()
    assert detail["status"] == "anchored"
    assert detail["tx_hash"].startswith("0x")
    assert detail["block_number"] > 0


def test_a_batch_is_stored_in_order_and_answered_one_result_each(robot, robot_api, upload):
    envelopes = [robot.seal(seq) for seq in (3, 4, 7)]
    answer = upload(robot_api, *envelopes)
    assert answer.status_code == 201
    results = answer.json()
    assert [r["seq"] for r in results] == [3, 4, 7]
    assert [r["digest"] for r in results] == [sm3.sm3_hex(data) for data in envelopes]
    assert Record.objects.filter(robot=robot.robot).count() == 3
    robot.robot.refresh_from_db()
    assert robot.robot.last_seq == 7


def test_a_batch_of_one_is_answered_as_a_list(robot, robot_api, upload):
    answer = upload(robot_api, robot.seal(1), batch=True)
    assert answer.status_code == 201
    assert isinstance(answer.json(), list)


# --- the forged node of issue 5: rejected, nothing stored ------------------------------------


def _forged_key_id(robot) -> bytes:
    """A random key's envelope relabelled with the owner's (public) key id."""
    data = bytearray(seal_for(robot.robot, sm4.generate_key(), seq=10))
    data[4:12] = envelope.key_id(robot.key)
    return bytes(data)


def test_a_forged_node_on_the_same_topic_is_rejected_and_nothing_stored(make_robot, upload):
    victim = make_robot()
    other = make_robot()
    victim_api = token_client(victim.token)
    assert upload(victim_api, victim.seal(5)).status_code == 201
    sibling, sibling_token = robot_create(owner=victim.owner, name="sibling")
    attempts = [
        # (case, client, envelope, status, error)
        (
            "no key: sealed under a random key",
            victim_api,
            seal_for(victim.robot, sm4.generate_key(), seq=10),
            403,
            "unknown_key",
        ),
        (
            "no key: a random key labelled with the owner's key id",
            victim_api,
            _forged_key_id(victim),
            403,
            "forged_envelope",
        ),
        (
            "wrong key: another owner's key",
            victim_api,
            seal_for(victim.robot, other.key, seq=10),
            403,
            "unknown_key",
        ),
        (
            "stale seq: the last one, other data",
            victim_api,
            victim.seal(5),
            409,
            "sequence_conflict",
        ),
        ("stale seq: an earlier one", victim_api, victim.seal(2), 409, "sequence_conflict"),
        (
            "another robot's token, same owner",
            token_client(sibling_token),
            victim.seal(10),
            403,
            "header_mismatch",
        ),
        (
            "another owner's robot token",
            token_client(other.token),
            victim.seal(10),
            403,
            "header_mismatch",
        ),
        (
            "another owner's robot, naming our owner",
            token_client(other.token),
            seal_for(other.robot, other.key, seq=10, owner=victim.owner.username),
            403,
            "header_mismatch",
        ),
    ]
    for case, client, data, status, error in attempts:
        before = Snapshot()
        answer = upload(client, data)
        assert (answer.status_code, answer.json()["error"]) == (status, error), case
        assert before.unchanged(), case
    assert Record.objects.filter(owner=victim.owner).count() == 1
    assert sibling.records.count() == Record.objects.filter(owner=other.owner).count() == 0


def test_a_forged_tag_is_logged_as_a_security_event(robot, robot_api, upload):
    assert upload(robot_api, _forged_key_id(robot)).status_code == 403
    event = SecurityEvent.objects.get()
    assert event.kind == SecurityEvent.Kind.FORGED_UPLOAD
    assert event.owner == robot.owner


def test_one_bad_envelope_refuses_the_whole_batch(robot, robot_api, upload):
    good = [robot.seal(seq) for seq in (1, 2)]
    bad = seal_for(robot.robot, sm4.generate_key(), seq=3)
    before = Snapshot()
    answer = upload(robot_api, *good, bad)
    assert answer.status_code == 403
    assert answer.json()["error"] == "unknown_key"
    assert before.unchanged()


def test_a_batch_out_of_order_is_refused(robot, robot_api, upload):
    before = Snapshot()
    answer = upload(robot_api, robot.seal(2), robot.seal(1))
    assert answer.status_code == 400
    assert answer.json()["error"] == "invalid_envelope"
    assert before.unchanged()


def test_an_envelope_under_a_rotated_key_is_accepted_for_an_hour_only(
    robot, robot_api, upload, django_capture_on_commit_callbacks
):
    with django_capture_on_commit_callbacks(execute=True):
        new_key = key_rotate(owner=robot.owner, sm4_key=sm4.generate_key())
    assert upload(robot_api, robot.seal(1)).status_code == 201
    robot.owner.keys.filter(key_id=envelope.key_id(robot.key).hex()).update(
        retired_at=timezone.now() - KEY_ROTATION_GRACE - timedelta(minutes=1)
    )
    before = Snapshot()
    answer = upload(robot_api, robot.seal(2))
    assert answer.status_code == 403
    assert answer.json()["error"] == "unknown_key"
    assert before.unchanged()
    assert new_key.is_current


# --- who may upload ----------------------------------------------------------------------------


def test_uploads_need_a_robot_token(robot, client):
    data = {"envelope": b64(robot.seal(1))}
    before = Snapshot()
    anonymous = client.post(RECORDS, data, content_type="application/json")
    assert anonymous.status_code == 401
    assert anonymous.json()["error"] == "not_authenticated"
    assert anonymous["WWW-Authenticate"] == "Token"
    owner_session = session_client(robot.owner).post(RECORDS, data, format="json")
    assert owner_session.status_code == 403
    assert owner_session.json()["error"] == "permission_denied"
    assert "robot token" in owner_session.json()["detail"]
    assert before.unchanged()


def test_a_session_upload_without_csrf_token_is_refused(robot):
    answer = session_client(robot.owner, enforce_csrf=True).post(
        RECORDS, {"envelope": b64(robot.seal(1))}, format="json"
    )
    assert answer.status_code == 403
    assert answer.json()["error"] == "permission_denied"
    assert "CSRF" in answer.json()["detail"]


def test_bad_credentials_are_refused_with_401(robot, client):
    body = {"envelope": b64(robot.seal(1))}
    before = Snapshot()
    for header in ("Token nope", "Token", "Token a b", "token ", "Token \u00e9t\u00e9", "Bearer x"):
        answer = client.post(
            RECORDS,
            body,
            content_type="application/json",
            HTTP_AUTHORIZATION=header.encode("utf-8").decode("latin-1"),
        )
        assert answer.status_code == 401, header
        assert answer.json()["error"] == "not_authenticated", header
    assert before.unchanged()


def test_a_revoked_token_stops_working_at_once(robot, robot_api, upload):
    assert upload(robot_api, robot.seal(1)).status_code == 201
    robot_token_revoke(robot=robot.robot)
    answer = upload(robot_api, robot.seal(2))
    assert answer.status_code == 401
    assert Record.objects.count() == 1


def test_a_disabled_owner_account_disables_its_robots(robot, robot_api, upload):
    robot.owner.user.is_active = False
    robot.owner.user.save()
    assert upload(robot_api, robot.seal(1)).status_code == 401
    assert Record.objects.count() == 0


# --- malformed requests: JSON errors, never a 500, nothing stored ----------------------------

_NESTED = b'{"envelope": ' + b"[" * 50_000 + b"]" * 50_000 + b"}"


_MALFORMED = [
    # (body, content type, status, error)
    (b"not json", "application/json", 400, "malformed_request"),
    (b"\xff\xfe{}", "application/json", 400, "malformed_request"),
    (b'{"envelope": NaN}', "application/json", 400, "malformed_request"),
    (b'{"envelope": ' + b"9" * 5000 + b"}", "application/json", 400, "malformed_request"),
    (_NESTED, "application/json", 400, "malformed_request"),
    (b"", "application/json", 400, "invalid_request"),
    (b"[]", "application/json", 400, "invalid_request"),
    (b'"AR"', "application/json", 400, "invalid_request"),
    (b"{}", "application/json", 400, "invalid_request"),
    (b'{"envelope": null}', "application/json", 400, "invalid_request"),
    (b'{"envelope": 12}', "application/json", 400, "invalid_request"),
    (b'{"envelope": 1e400}', "application/json", 400, "invalid_request"),
    (b'{"envelope": ""}', "application/json", 400, "invalid_request"),
    (b'{"envelope": "not base64!"}', "application/json", 400, "invalid_request"),
    (b'{"envelope": "QVI="}', "application/json", 400, "invalid_envelope"),
    (b'{"envelope": "\\u00e9\\u00e9\\u00e9\\u00e9"}', "application/json", 400, "invalid_request"),
    (b'{"envelope": {"a": 1}}', "application/json", 400, "invalid_request"),
    (b'{"envelopes": []}', "application/json", 400, "invalid_request"),
    (b'{"envelopes": "QVI="}', "application/json", 400, "invalid_request"),
    (b'{"envelopes": [1, 2]}', "application/json", 400, "invalid_request"),
    (b'{"envelopes": [null]}', "application/json", 400, "invalid_request"),
    (b'{"envelopes": ["QVI="], "envelope": "QVI="}', "application/json", 400, "invalid_request"),
    (b"envelope=QVI%3D", "application/x-www-form-urlencoded", 415, "unsupported_media_type"),
    (b"AR\x01\x01", "application/octet-stream", 415, "unsupported_media_type"),
]


def test_malformed_uploads_get_a_json_error_and_change_nothing(robot_api):
    before = Snapshot()
    for body, content_type, status, error in _MALFORMED:
        answer = robot_api.generic("POST", RECORDS, body, content_type=content_type)
        case = body[:60]
        assert answer.status_code == status, (case, answer.content[:300])
        assert answer["Content-Type"] == "application/json", case
        assert answer.json()["error"] == error, case
        assert isinstance(answer.json()["detail"], str), case
    assert before.unchanged()


def test_a_validation_error_names_the_field(robot_api):
    answer = robot_api.post(RECORDS, {"envelopes": ["QVI=", "%%%"]}, format="json")
    assert answer.status_code == 400
    assert answer.json()["detail"] == "envelopes[1]: not valid base64"
    assert answer.json()["fields"] == {"envelopes": {"1": ["not valid base64"]}}


def test_envelopes_with_bad_headers_are_refused(robot, robot_api, upload):
    bad_fields = [
        ({"owner": "someone-else"}, 403, "header_mismatch"),
        ({"robot": "not-this-robot"}, 403, "header_mismatch"),
        ({"topic": "/x" * 200}, 400, "invalid_envelope"),
        ({"type": "a/" + "b" * 300}, 400, "invalid_envelope"),
        ({"time": "2026-01-01T00:00:00+02:00"}, 400, "invalid_envelope"),
        ({"time": "yesterday"}, 400, "invalid_envelope"),
        ({"seq": -1}, 400, "invalid_envelope"),
        ({"seq": 2**63}, 400, "invalid_envelope"),
        ({"seq": "1"}, 400, "invalid_envelope"),
    ]
    before = Snapshot()
    for change, status, error in bad_fields:
        header = {
            "owner": robot.owner.username,
            "robot": str(robot.robot.id),
            "topic": "/chatter",
            "type": "std_msgs/String",
            "seq": 1,
            "time": "2026-01-01T00:00:00Z",
            **change,
        }
        answer = upload(robot_api, _sealed_without_checks(robot.key, header))
        assert (answer.status_code, answer.json()["error"]) == (status, error), change
    assert before.unchanged()


def _sealed_without_checks(key: bytes, header: dict) -> bytes:
    """An envelope sealed under `key` whatever its header holds (the library would refuse)."""
    header_bytes = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    nonce = bytes(12)
    prefix = (
        b"AR\x01\x01" + envelope.key_id(key) + nonce + len(header_bytes).to_bytes(4, "big")
    ) + header_bytes
    return prefix + sm4.gcm_encrypt(key, nonce, b"{}", prefix)


# --- size and rate limits ---------------------------------------------------------------------


def test_an_envelope_above_the_size_limit_gets_413(robot, robot_api, upload, settings):
    settings.ENVELOPE_MAX_BYTES = 4096
    before = Snapshot()
    answer = upload(robot_api, robot.seal(1, plaintext=b"x" * 5000))
    assert answer.status_code == 413
    assert answer.json()["error"] == "envelope_too_large"
    assert before.unchanged()
    assert upload(robot_api, robot.seal(1, plaintext=b"x" * 3000)).status_code == 201


def test_a_request_body_above_the_limit_gets_a_json_413(robot, robot_api, upload, settings):
    settings.DATA_UPLOAD_MAX_MEMORY_SIZE = 10_000
    envelopes = [robot.seal(seq, plaintext=b"x" * 1000) for seq in range(1, 11)]
    before = Snapshot()
    answer = upload(robot_api, *envelopes)
    assert answer.status_code == 413
    assert answer["Content-Type"] == "application/json"
    assert answer.json()["error"] == "request_too_large"
    assert before.unchanged()


def test_too_many_envelopes_in_one_upload(robot_api):
    before = Snapshot()
    answer = robot_api.post(RECORDS, {"envelopes": ["QVI="] * 1001}, format="json")
    assert answer.status_code == 400
    assert answer.json()["fields"]["envelopes"]
    assert before.unchanged()


def test_uploads_above_the_rate_limit_get_429_with_retry_after(
    robot, robot_api, upload, settings, make_robot
):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "upload": "2/minute",
        },
    }
    assert upload(robot_api, robot.seal(1)).status_code == 201
    assert upload(robot_api, robot.seal(2)).status_code == 201
    before = Snapshot()
    answer = upload(robot_api, robot.seal(3))
    assert answer.status_code == 429
    assert answer.json()["error"] == "rate_limited"
    assert 0 < int(answer["Retry-After"]) <= 60
    assert before.unchanged()
    # Per robot, and reading is not an upload.
    assert robot_api.get(RECORDS).status_code == 200
    other = make_robot()
    assert upload(token_client(other.token), other.seal(1)).status_code == 201


def test_an_upload_counts_its_owners_limit_and_its_robots_in_one_round_trip(
    robot, robot_api, upload, settings, monkeypatch
):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "user": "2/minute",
        },
    }
    pipelines = []
    real = authentication.get_redis

    class Counting:
        def pipeline(self, **options):
            pipelines.append(options)
            return real().pipeline(**options)

    monkeypatch.setattr(authentication, "get_redis", Counting)
    assert upload(robot_api, robot.seal(1)).status_code == 201
    assert len(pipelines) == 1
    counted = {
        key.decode().removeprefix(redis_key("throttle", "")).split(":")[0]
        for key in get_redis().scan_iter(redis_key("throttle", "*"))
    }
    assert counted == {"user", "upload"}
    # The owner's limit holds across its robots: a second robot of the owner gets the rest.
    other, token = robot_create(owner=robot.owner, name="second")
    assert upload(token_client(token), seal_for(other, robot.key, seq=1)).status_code == 201
    before = Snapshot()
    refused = upload(token_client(token), seal_for(other, robot.key, seq=2))
    assert refused.status_code == 429
    assert before.unchanged()


def test_anonymous_requests_are_rate_limited_per_address(client, settings):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "anon": "3/minute",
        },
    }
    statuses = [client.get("/api/v1/sm2-public-key/").status_code for _ in range(3)]
    assert statuses == [200, 200, 200]
    # A client cannot reset its budget by claiming another address.
    spoofed = client.get("/api/v1/sm2-public-key/", HTTP_X_FORWARDED_FOR="10.1.2.3")
    assert spoofed.status_code == 429
    assert spoofed.json()["error"] == "rate_limited"


def test_a_warm_upload_reads_the_owners_keys_once_and_the_deployment_not_at_all(
    robot, robot_api, upload, monkeypatch
):
    """The identity check and the unsealing share one read of the owner's keys; the chain
    client keeps the deployment's address (re-read every DEPLOYMENT_RECHECK_SECONDS)."""
    # However slow the machine: the two uploads within one interval.
    monkeypatch.setattr(chain_services, "DEPLOYMENT_RECHECK_SECONDS", 3600)
    assert upload(robot_api, robot.seal(1)).status_code == 201
    with CaptureQueriesContext(connection) as queries:
        assert upload(robot_api, robot.seal(2)).status_code == 201
    tables = [q["sql"] for q in queries]
    assert len([sql for sql in tables if '"accounts_ownerkey"' in sql]) == 1, tables
    assert not [sql for sql in tables if '"chainworker_deployment"' in sql], tables


@pytest.mark.parametrize(
    ("accept", "query", "status"),
    [
        (None, "", 201),
        ("*/*", "", 201),
        ("application/json", "", 201),
        ("application/json; indent=2", "", 201),
        ("text/html, application/json;q=0.5", "", 201),
        ("text/html", "", 406),
        ("image/png, text/*", "", 406),
        (None, "?format=json", 201),
        (None, "?format=xml", 404),
    ],
)
def test_the_api_answers_json_to_whoever_accepts_it_and_406_otherwise(
    robot, robot_api, django_capture_on_commit_callbacks, accept, query, status
):
    """Negotiated as DRF does, the common Accept headers without parsing; a refusal stores
    nothing."""
    headers = {} if accept is None else {"HTTP_ACCEPT": accept}
    with django_capture_on_commit_callbacks(execute=True):
        answer = robot_api.post(
            RECORDS + query, {"envelope": b64(robot.seal(1))}, format="json", **headers
        )
    assert answer.status_code == status
    assert answer["Content-Type"].startswith("application/json")
    assert Record.objects.count() == (1 if status == 201 else 0)
    if status == 406:
        assert answer.json()["error"] == "not_acceptable"
