"""The series' check in the workers (sharing.tasks.series_verify, sharing/verification/
series_check.py): the same verdicts as one check per record on a mix of good, tampered,
unsigned-under-a-paired-robot and unanchored records, the verdicts written in bulk per slice
under the plot's one access line, and the answer sealed for the read: no plaintext in what the
task hands back, nor anywhere in Redis after a series. Against the session's anvil."""

import base64
import json
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext

from accounts.keywrap import UnwrapFailed
from sharing import tasks
from sharing.models import Access, Record, Verdict
from sharing.services.uploads import record_create_batch
from sharing.verification import opening
from sharing.verification.access import accesses_open
from sharing.verification.answers import answer_key_make, answer_open
from sharing.verification.check import records_verify
from smcrypto import envelope, provenance
from smcrypto.errors import AuthenticationFailed
from tests.api.conftest import session_client
from tests.support.tampering import stored_behind_the_portal, tamper

pytestmark = pytest.mark.django_db

API = "/api/v1/records/series/"
TOPIC = "/robot/odom"
MARKER = "series-marker-7f3a"  # in every record's plaintext, never in clear in Redis
T0 = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(minutes=10)


def _body(seq: int) -> bytes:
    return json.dumps({"K": {"position": {"x": seq + 0.25, "y": -seq}, "note": MARKER}}).encode()


def _batch(setup, seqs: range, first_topic_seq: int) -> list[bytes]:
    """A v2 batch signed once by the paired robot, one record a second from T0 + seq s."""
    records = [
        (
            {
                "owner": setup.owner.username,
                "robot": str(setup.robot.id),
                "topic": TOPIC,
                "type": "nav_msgs/Odometry",
                "seq": seq,
                "time": (T0 + timedelta(seconds=seq)).isoformat().replace("+00:00", "Z"),
                "topic_seq": first_topic_seq + at,
            },
            _body(seq),
        )
        for at, seq in enumerate(seqs)
    ]
    headers = provenance.sign_batch(*setup.signing_key, records)
    return [
        envelope.seal(setup.key, header, body)
        for header, (_, body) in zip(headers, records, strict=True)
    ]


def _mixed(setup, capture) -> dict[str, list[Record]]:
    """Good v2 records in two batches, one of them tampered with, an unsigned record written
    under the paired robot behind the portal's back (anchored), and a batch not anchored."""
    with capture(execute=True):
        first = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(1, 6), 0))
        second = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(6, 10), 5))
    forged = stored_behind_the_portal(
        setup,
        setup.seal(
            20,
            signing_key=None,
            plaintext=_body(20),
            time=(T0 + timedelta(seconds=20)).isoformat().replace("+00:00", "Z"),
        ),
        capture,
        signer="",
    )
    with capture(execute=False):  # its anchoring job never runs
        pending = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(30, 33), 9))
    tamper(second[1])
    return {"good": first + second, "forged": [forged], "pending": pending}


def _query(setup) -> dict[str, str]:
    return {
        "robot": str(setup.robot.pk),
        "topic": TOPIC,
        "fields": "position.x,position.y",
        "since": T0.isoformat(),
        "until": (T0 + timedelta(minutes=5)).isoformat(),
        "points": "1000",
    }


def test_the_series_gives_each_record_the_verdict_of_one_check_per_record(
    make_paired_robot, django_capture_on_commit_callbacks, redis_client, settings, monkeypatch
):
    setup = make_paired_robot("alice")
    made = _mixed(setup, django_capture_on_commit_callbacks)
    assert {r.status for r in made["pending"]} == {Record.Status.PENDING}
    every = sorted(
        (record for records in made.values() for record in records), key=lambda r: r.captured_at
    )
    one_by_one = {
        record.pk: records_verify(record_ids=[record.pk], viewer_id=setup.owner.pk)[0].verdict
        for record in every
    }
    assert sorted(v.outcome for v in one_by_one.values()) == sorted(
        ["verified"] * 8 + ["tampered", "signature_refused"] + ["not_anchored_yet"] * 3
    )

    monkeypatch.setattr(opening, "SERIES_BATCH", 4)  # four slices, each its own task
    with CaptureQueriesContext(connection) as queries:
        answer = session_client(setup.owner).get(API, _query(setup))
    assert answer.status_code == 200, answer.content
    body = answer.json()
    counts = ("source_records", "verified", "refused", "not_anchored_yet")
    assert tuple(body[name] for name in counts) == (13, 8, 2, 3)
    verified = sorted(
        (r for r in every if one_by_one[r.pk].outcome == "verified"), key=lambda r: r.captured_at
    )
    assert body["points"] == [
        [r.captured_at.timestamp(), r.seq + 0.25, -float(r.seq)] for r in verified
    ]

    # The plot's one line, a verdict per record in bulk: one INSERT per slice, each the
    # outcome one check per record gave, at or above the block the record was anchored in.
    (access,) = Access.objects.filter(kind=Access.Kind.PLOT)
    assert (access.count, access.viewer_id, access.topic) == (13, setup.owner.pk, TOPIC)
    verdicts = {v.record_id: v for v in access.verdicts.all()}
    assert {pk: v.outcome for pk, v in verdicts.items()} == {
        pk: v.outcome for pk, v in one_by_one.items()
    }
    for record in every:
        verdict = verdicts[record.pk]
        assert verdict.block_number >= (record.block_number or 0)
        assert verdict.computed_digest == one_by_one[record.pk].computed_digest
    inserts = [q["sql"] for q in queries.captured_queries if q["sql"].startswith("INSERT")]
    assert sum('"sharing_verdict"' in sql for sql in inserts) == 4

    # Nothing of any record's plaintext in Redis after the series (cache, broker, results).
    for key in redis_client.scan_iter("*"):
        kind = redis_client.type(key)
        values = {
            b"string": lambda k: [redis_client.get(k)],
            b"list": lambda k: redis_client.lrange(k, 0, -1),
            b"hash": lambda k: list(redis_client.hgetall(k).values()),
            b"set": lambda k: list(redis_client.smembers(k)),
        }.get(kind, lambda k: [])(key)
        for value in values:
            assert MARKER.encode() not in (value or b""), key


def test_the_task_hands_back_only_the_rows_sealed_for_its_read(
    make_paired_robot, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(1, 4), 0))
    accesses = accesses_open(
        kind=Access.Kind.PLOT,
        viewer_id=setup.owner.pk,
        records=records,
        credential="session",
        token_id=None,
    )
    key = answer_key_make()
    answer = tasks.series_verify(
        [str(r.pk) for r in records],
        setup.owner.pk,
        "session",
        None,
        {str(k): v for k, v in accesses.items()},
        ["position.x"],
        key.read_id,
        key.wrapped,
        2,
    )
    sent = json.dumps(answer)
    for clear in (MARKER, "1.25", "position"):  # neither the content nor the values
        assert clear not in sent
    assert set(answer) == {"verified", "rows"}
    assert answer["verified"] == 3
    rows = answer_open(key=key, part=2, sealed=answer["rows"])
    assert rows == [[r.captured_at.timestamp(), r.seq + 0.25] for r in records]
    assert Verdict.objects.filter(access_id__in=accesses.values(), outcome="verified").count() == 3
    # Only this read's key opens it, and only as the part it was sealed as.
    with pytest.raises(AuthenticationFailed):
        answer_open(key=key, part=1, sealed=answer["rows"])
    with pytest.raises(AuthenticationFailed):
        answer_open(key=answer_key_make(), part=2, sealed=answer["rows"])
    # The wrapped key names its read: sent with another read's id, the worker cannot open it.
    other = answer_key_make()
    verdicts = Verdict.objects.count()
    with pytest.raises(UnwrapFailed):
        tasks.series_verify(
            [str(records[0].pk)],
            setup.owner.pk,
            "session",
            None,
            {str(k): v for k, v in accesses.items()},
            ["position.x"],
            other.read_id,
            key.wrapped,
            0,
        )
    assert Verdict.objects.count() == verdicts  # refused before any check
    assert key.key not in base64.b64decode(key.wrapped)


def _slice_checked(setup, records: list[Record]) -> tuple[dict, list]:
    """series_rows_check of `records` as one slice under a fresh plot line: the answer and its
    rows opened."""
    accesses = accesses_open(
        kind=Access.Kind.PLOT,
        viewer_id=setup.owner.pk,
        records=records,
        credential="session",
        token_id=None,
    )
    key = answer_key_make()
    answer = tasks.series_verify(
        [str(r.pk) for r in records],
        setup.owner.pk,
        "session",
        None,
        {str(k): v for k, v in accesses.items()},
        ["position.x"],
        key.read_id,
        key.wrapped,
        0,
    )
    return answer, answer_open(key=key, part=0, sealed=answer["rows"])


def test_every_record_of_a_slice_is_checked_a_tampered_one_inside_it_refused(
    make_paired_robot, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(1, 8), 0))
    tamper(records[3])  # in the middle of the slice and of its v2 batch
    answer, rows = _slice_checked(setup, records)
    assert answer["verified"] == 6
    assert rows == [[r.captured_at.timestamp(), r.seq + 0.25] for r in records if r != records[3]]
    outcomes = dict(Verdict.objects.values_list("record_id", "outcome"))
    assert outcomes == {r.pk: "tampered" if r == records[3] else "verified" for r in records}, (
        "one verdict per record of the slice, the tampered one refused"
    )
    records[3].refresh_from_db()
    assert records[3].tampered_at is not None


def test_a_slice_reads_what_its_check_needs_at_once_whatever_its_size(
    make_paired_robot, django_capture_on_commit_callbacks
):
    """The worker reads only some columns of each record: a column the check needed but did
    not read would be read per record (Django's deferred fields), here seen as more queries
    for a bigger slice."""
    setup = make_paired_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=setup.robot, envelopes=_batch(setup, range(1, 9), 0))
    queries = []
    for size in (2, 8):
        _slice_checked(setup, records[:size])  # warm: the keys and the chain's reads
        with CaptureQueriesContext(connection) as captured:
            answer, rows = _slice_checked(setup, records[:size])
        assert (answer["verified"], len(rows)) == (size, size)
        queries.append(len(captured.captured_queries))
    assert queries[0] == queries[1], queries
