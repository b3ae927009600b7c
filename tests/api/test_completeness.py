"""`GET /api/v1/records/completeness/` and the series' `streams`: every record counted, for the
owner and a grantee within its scope, nothing for anyone else, bad input a 400.

Records are real uploads of a paired robot (signed, anchored inline); their `topic_seq` is set
on the stored rows as the v2 ingest stores it (the agent's count, 0, 1, 2 ...). A record lost
behind the portal's back is its row and stored file removed; an owner's deletion and a
retention sweep go through the portal's own services."""

import uuid
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from accounts.models import Robot
from accounts.services.api_tokens import owner_token_revoke
from core.redis_client import get_redis
from sharing.cache import _key as cache_key
from sharing.grant_terms import grant_terms_make
from sharing.models import Record
from sharing.services.deletion import record_delete, retention_apply
from sharing.services.grants import grant_create
from sharing.storage import envelope_storage
from tests.api.conftest import session_client, token_client
from tests.pages.conftest import odometry, upload  # noqa: F401  (the fixture)

pytestmark = pytest.mark.django_db

API = "/api/v1/records/completeness/"
SERIES = "/api/v1/records/series/"
ODOM = "/robot/odom"
T0 = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(minutes=30)


def _iso(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


def stream_upload(upload, setup, count, *, topic=ODOM, start=T0, first=0):  # noqa: F811
    """`count` signed records of one topic, a second apart, numbered from `first` as the
    agent counts."""
    made = []
    for number in range(count):
        record = upload(
            setup,
            max(Robot.objects.get(pk=setup.robot.pk).last_seq + 1, 1),
            topic=topic,
            plaintext=odometry(setup.owner.username, float(number), 0.0),
            time=_iso(start + timedelta(seconds=number)),
        )
        Record.objects.filter(pk=record.pk).update(topic_seq=first + number)
        made.append(record)
    return made


def lost(record: Record) -> None:
    """The record dropped behind the portal's back: its row and its stored envelope gone."""
    get_redis().delete(cache_key(record.pk))
    envelope_storage().delete(record.storage_name)
    Record.objects.filter(pk=record.pk).delete()


@pytest.fixture
def alice(make_paired_robot):
    return make_paired_robot("alice")


@pytest.fixture
def odom(alice, upload):  # noqa: F811
    """Six records of /robot/odom: #2 lost, #3 deleted by alice; the rest live."""
    made = stream_upload(upload, alice, 6)
    lost(made[2])
    record_delete(owner=alice.owner, record_id=made[3].pk, actor=alice.owner.user)
    return made


def _expected(alice, odom):
    deleted_at = Record.objects.get(pk=odom[3].pk).deleted_at
    return {
        "signer": alice.robot.key_hash,
        "topic": ODOM,
        "robot": str(alice.robot.pk),
        "first": 0,
        "last": 5,
        "count": 4,
        "gaps": [
            {"from": 2, "to": 2, "reason": "missing"},
            {"from": 3, "to": 3, "reason": "deleted", "at": deleted_at.isoformat()},
        ],
    }


def test_the_owner_is_told_what_is_missing_and_what_was_deleted_when(alice, odom, upload):  # noqa: F811
    stream_upload(upload, alice, 2, topic="/robot/scan")
    client = session_client(alice.owner)
    answer = client.get(API, {"robot": str(alice.robot.pk), "topic": ODOM})
    assert answer.status_code == 200, answer.content
    assert answer.json() == {"streams": [_expected(alice, odom)], "uncounted": 0}
    # No filter: both topics of the robot; a window that ends before the gaps sees none.
    everything = client.get(API).json()["streams"]
    assert [(s["topic"], s["count"], len(s["gaps"])) for s in everything] == [
        (ODOM, 4, 2),
        ("/robot/scan", 2, 0),
    ]
    early = client.get(API, {"topic": ODOM, "until": _iso(T0 + timedelta(seconds=2))}).json()
    assert early["streams"][0] | {"gaps": None} == {
        **_expected(alice, odom),
        "last": 1,
        "count": 2,
        "gaps": None,
    }
    assert early["streams"][0]["gaps"] == []


def test_a_retention_sweep_is_named_with_when(alice, upload, settings):  # noqa: F811
    made = stream_upload(upload, alice, 5, start=timezone.now() - timedelta(days=3))
    # The two newest stay: captured within the robot's retention.
    Record.objects.filter(pk__in=[made[3].pk, made[4].pk]).update(captured_at=timezone.now())
    alice.robot.retention_days = 1
    alice.robot.save(update_fields=["retention_days"])
    assert retention_apply()["deleted"] == 3
    (stream,) = session_client(alice.owner).get(API).json()["streams"]
    swept = Record.objects.filter(pk=made[2].pk).values_list("deleted_at", flat=True).get()
    assert (stream["first"], stream["last"], stream["count"]) == (0, 4, 2)
    assert stream["gaps"] == [
        {"from": 0, "to": 2, "reason": "retention", "at": swept.isoformat()},
    ]


def test_an_owner_token_with_read_reads_it_and_a_revoked_one_is_refused(
    alice, odom, make_owner_token
):
    token, key = make_owner_token(alice.owner, scopes=("read",))
    client = token_client(key)
    answer = client.get(API, {"robot": str(alice.robot.pk)})
    assert answer.status_code == 200
    assert answer.json()["streams"] == [_expected(alice, odom)]
    # Stolen, then revoked by its owner: refused, nothing answered.
    owner_token_revoke(token=token, actor=alice.owner.user)
    refused = client.get(API, {"robot": str(alice.robot.pk)})
    assert refused.status_code == 401
    assert "streams" not in refused.json()
    # A token without `read` and a robot's own token read nothing of it.
    _, share_only = make_owner_token(alice.owner, scopes=("share",))
    assert token_client(share_only).get(API).json()["error"] == "insufficient_scope"
    robot_answer = token_client(alice.token).get(API)
    assert robot_answer.status_code == 403
    assert "streams" not in robot_answer.json()
    assert token_client("not-a-token").get(API).status_code == 401


def test_a_grantee_reads_it_within_its_scope_only(
    alice,
    odom,
    upload,  # noqa: F811
    make_owner,
    django_capture_on_commit_callbacks,
):
    stream_upload(upload, alice, 3, topic="/robot/scan")
    bob, carol = make_owner("bob"), make_owner("carol")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(
            owner=alice.owner, grantee=bob, terms=grant_terms_make(owner=alice.owner, topics=[ODOM])
        )
    bob_client = session_client(bob)
    answer = bob_client.get(API, {"robot": str(alice.robot.pk)})
    assert answer.status_code == 200
    # Only the topic of the grant: the other one answers as a topic that does not exist.
    assert answer.json() == {"streams": [_expected(alice, odom)], "uncounted": 0}
    nothing = {"streams": [], "uncounted": 0}
    out_of_scope = bob_client.get(API, {"robot": str(alice.robot.pk), "topic": "/robot/scan"})
    no_such_topic = bob_client.get(API, {"robot": str(alice.robot.pk), "topic": "/nothing"})
    no_such_robot = bob_client.get(API, {"robot": str(uuid.uuid4())})
    assert out_of_scope.json() == no_such_topic.json() == no_such_robot.json() == nothing
    # Someone with no grant learns nothing of alice's robot.
    for query in ({"robot": str(alice.robot.pk)}, {"topic": ODOM}, {}):
        stranger = session_client(carol).get(API, query)
        assert stranger.status_code == 200
        assert stranger.json() == nothing


@pytest.mark.parametrize(
    "query",
    [
        {"robot": "not-a-uuid"},
        {"robot": ""},
        {"since": "yesterday"},
        {"until": "2026-13-01T00:00:00Z"},
        {"since": "2026-11-30T12:00:00Z", "until": "2026-11-30T12:00:00Z"},
        {"since": "2026-11-30T12:00:00Z", "until": "2026-11-30T11:00:00Z"},
        {"since": "0001-01-01T00:00:00+14:00"},
        {"until": "9999-12-31T23:59:59-14:00"},
        {"topic": "/odom\x00"},
        {"topic": "x" * 256},
    ],
)
def test_bad_parameters_are_a_400_that_says_which(alice, query):
    answer = session_client(alice.owner).get(API, query)
    assert answer.status_code == 400, answer.content
    body = answer.json()
    assert body["error"] == "invalid_request"
    assert "streams" not in body


def test_the_answer_is_a_few_queries_whatever_the_window_holds(alice, upload):  # noqa: F811
    made = stream_upload(upload, alice, 12)
    lost(made[5])
    record_delete(owner=alice.owner, record_id=made[8].pk, actor=alice.owner.user)
    client = session_client(alice.owner)
    # The session's first request reads more of it than the next ones, and alerts the gap.
    client.get(API)
    with CaptureQueriesContext(connection) as few:
        client.get(API)
    more_made = stream_upload(upload, alice, 12, start=T0 + timedelta(minutes=1), first=12)
    lost(more_made[3])
    record_delete(owner=alice.owner, record_id=more_made[6].pk, actor=alice.owner.user)
    client.get(API)  # alerts the new missing gap (tests/pages/test_completeness_pages.py)
    with CaptureQueriesContext(connection) as more:
        client.get(API)
    assert len(more) == len(few)


def test_the_series_carries_the_streams_of_its_range(alice, odom):
    query = {
        "robot": str(alice.robot.pk),
        "topic": ODOM,
        "fields": "position.x",
        "since": _iso(T0),
        "until": _iso(T0 + timedelta(minutes=1)),
    }
    answer = session_client(alice.owner).get(SERIES, query)
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert (body["source_records"], body["verified"], body["refused"]) == (4, 4, 0)
    assert body["streams"] == [_expected(alice, odom)]
    assert body["uncounted"] == 0
    # The same as the completeness answer for that robot, topic and range.
    completeness = session_client(alice.owner).get(
        API, {key: query[key] for key in ("robot", "topic", "since", "until")}
    )
    assert completeness.json()["streams"] == body["streams"]


def test_an_owner_above_the_rate_limit_gets_429(alice, settings):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "user": "2/minute",
        },
    }
    client = session_client(alice.owner)
    assert [client.get(API).status_code for _ in range(2)] == [200, 200]
    answer = client.get(API)
    assert answer.status_code == 429
    assert answer.json()["error"] == "rate_limited"
    assert 0 < int(answer["Retry-After"]) <= 60
