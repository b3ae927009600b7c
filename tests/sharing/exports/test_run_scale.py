"""Issue 35: exports beyond the old cap of 5,000 records, streamed batch by batch in constant
memory, opened with the `mcap` reader and checked by authros_verify; the count of a selection
shown before submitting, and a selection above EXPORT_MAX_RECORDS refused with its count.
"""

import io
import json
import os

import pytest
from django.urls import reverse
from mcap.reader import make_reader

from authros_verify import ChainReader, verify
from sharing.exports import run, selection
from sharing.exports.create import export_create
from sharing.models import Export
from sharing.selection import RecordSelection
from sharing.services.uploads import record_create_batch
from smcrypto import sm4
from smcrypto.stream import SEGMENT_SIZE, SealedWriter, sealed_open
from tests.api.conftest import session_client
from tests.authros_verify.conftest import export_files

pytestmark = pytest.mark.django_db

MANY = 6_000


@pytest.fixture
def many(make_robot, django_capture_on_commit_callbacks):
    """6,000 small String records of one robot, anchored (one upload, one tree)."""
    setup = make_robot("alice")
    envelopes = [
        setup.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            time=f"2026-05-01T{seq // 3600:02d}:{seq // 60 % 60:02d}:{seq % 60:02d}Z",
            plaintext=json.dumps({"K": {"data": str(seq)}, "Owner": "alice"}).encode(),
        )
        for seq in range(1, MANY + 1)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    return setup


def test_an_export_beyond_5000_records_streams_in_batches_and_verifies(
    many, deployed, settings, monkeypatch, django_capture_on_commit_callbacks
):
    settings.EXPORT_BATCH = 500
    batches: list[int] = []
    checked = run._verified

    def counting(batch, *args):
        batches.append(len(batch))
        return checked(batch, *args)

    monkeypatch.setattr(run, "_verified", counting)
    buffered: list[int] = []
    write = SealedWriter.write

    def watched(self, data):
        written = write(self, data)
        buffered.append(self.buffered)
        return written

    monkeypatch.setattr(SealedWriter, "write", watched)

    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=many.owner)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    assert (export.total, export.exported, export.excluded) == (MANY, MANY, [])
    # The design that keeps memory flat: the records come 500 at a time, never all at once,
    # and the sealed files never hold more than one segment of plaintext.
    assert batches == [500] * (MANY // 500)
    assert max(buffered) <= SEGMENT_SIZE
    assert export.bundle_size > 2 * SEGMENT_SIZE  # so that several segments were sealed

    mcap, bundle = export_files(export)
    data = [
        json.loads(message.data)["data"] if channel.message_encoding == "json" else None
        for _schema, channel, message in make_reader(io.BytesIO(mcap)).iter_messages()
    ]
    assert len(data) == MANY
    report = verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed][:3])
    assert len(report.records) == MANY


def test_the_count_is_shown_before_submitting_and_an_over_limit_selection_is_refused(
    many, settings, django_capture_on_commit_callbacks
):
    client = session_client(many.owner)
    answer = client.get("/api/v1/exports/count/", {"topics": ["/chatter"]})
    assert answer.status_code == 200, answer.content
    assert answer.json() == {
        "count": MANY,
        "limit": settings.EXPORT_MAX_RECORDS,
        "exportable": True,
        "refusal": None,
    }
    window = {"since": "2026-05-01T00:00:00Z", "until": "2026-05-01T00:01:40Z"}
    assert client.get("/api/v1/exports/count/", window).json()["count"] == 99
    assert client.get("/api/v1/exports/count/", {"since": "yesterday"}).status_code == 400

    # The page without JavaScript: "Count records" answers with the count, exports nothing.
    page = client.post(reverse("exports"), {"topics": ["/chatter"], "count": "1"})
    assert page.status_code == 200
    assert 'data-count="6000"' in page.content.decode()
    assert not Export.objects.exists()

    settings.EXPORT_MAX_RECORDS = 5_000
    refused = client.get("/api/v1/exports/count/").json()
    assert (refused["count"], refused["exportable"]) == (MANY, False)
    assert "6,000 records" in refused["refusal"]
    answer = client.post("/api/v1/exports/", {}, format="json")
    assert answer.status_code == 400
    assert answer.json()["error"] == "invalid_selection"
    assert "6,000 records" in answer.json()["detail"]
    page = client.post(reverse("exports"), {"count": "1"})
    assert page.status_code == 400
    assert "6,000 records" in page.content.decode()
    assert not Export.objects.exists()


@pytest.mark.parametrize("size", [0, 1, SEGMENT_SIZE, 3 * SEGMENT_SIZE + 7])
def test_a_sealed_file_opens_whole_and_refuses_any_cut_or_change(size):
    key = sm4.generate_key()
    plaintext = os.urandom(size)
    sealed = io.BytesIO()
    writer = SealedWriter(sealed, key)
    for start in range(0, size, 100_003):
        writer.write(plaintext[start : start + 100_003])
        assert writer.buffered <= SEGMENT_SIZE
    writer.close()
    data = sealed.getvalue()
    assert b"".join(sealed_open(io.BytesIO(data), key)) == plaintext
    segment = SEGMENT_SIZE + 16
    header = len(data) - (size // SEGMENT_SIZE) * segment - (size % SEGMENT_SIZE + 16)
    for broken in (
        data[:-1],  # cut in the last segment
        data[: header + segment] if size > SEGMENT_SIZE else data[:header],  # cut at a boundary
        data[:-5] + bytes([data[-5] ^ 1]) + data[-4:],  # a changed byte
    ):
        with pytest.raises(Exception):  # noqa: B017, PT011 (AuthenticationFailed or InvalidData)
            b"".join(sealed_open(io.BytesIO(broken), key))


def test_batches_take_every_record_once_in_order_when_capture_times_tie(
    make_robot, django_capture_on_commit_callbacks
):
    """Keyset batches on (captured_at, seq, id): records captured at the same instant across
    a batch's edge are neither repeated nor skipped."""
    setup = make_robot("alice")
    times = ["2026-05-01T00:00:00Z"] * 5 + ["2026-05-01T00:00:01Z"] * 4 + ["2026-05-01T00:00:02Z"]
    envelopes = [setup.seal(seq, time=time) for seq, time in enumerate(times, start=1)]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    records = selection.export_records(setup.owner, RecordSelection())
    for size in (1, 2, 3, 4, 7, 10, 11):
        taken = [r.seq for batch in run.export_batches(records, size) for r in batch]
        assert taken == list(range(1, len(times) + 1)), size
