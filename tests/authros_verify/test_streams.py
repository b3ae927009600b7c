"""Provenance v2 in an export and in authros-verify: records signed one batch at a time (as the
agent signs an upload), exported by the portal's own exporter and checked against the session's
anvil. One SM2 verification per batch, in the export and in the verifier; every record counted
per stream by its signed topic_seq, every gap named (`missing` for a record dropped behind the
portal's back, `deleted` and `retention` with when), `--complete` failing on any; the MCAP file
read as a stream, compressed chunks included.

Record.topic_seq is set on the rows in the setup (from each envelope's header) for the case
where the ingest does not store it yet; once it does, setting it again changes nothing.
"""

import base64
import copy
import io
import json
import subprocess
import sys
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType

from authros_verify import BUNDLE_FORMAT, BUNDLE_FORMAT_V2, bundle_digest, bundle_serialise
from authros_verify import verify as export_verify
from authros_verify.__main__ import main
from core.redis_client import get_redis
from sharing.cache import _key as cache_key
from sharing.exports.create import export_create
from sharing.models import Export, Record
from sharing.services.deletion import record_delete, retention_apply
from sharing.services.uploads import record_create_batch
from sharing.storage import envelope_storage
from smcrypto import envelope, provenance, sm2
from smcrypto.sm3 import sm3_hex
from tests.authros_verify.conftest import export_files, mcap_rewritten, recomputed
from tests.support.harness import REPO_ROOT
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

T0 = datetime(2026, 5, 1, 12, 0, 0, tzinfo=UTC)
CHATTER, ODOM = "/chatter", "/odom"
# Two upload batches of two topics, in capture order: (topic, topic_seq) of each record.
BATCHES = [
    [(CHATTER, 0), (ODOM, 0), (CHATTER, 1), (ODOM, 1), (CHATTER, 2), (ODOM, 2), (CHATTER, 3)],
    [(CHATTER, 4), (CHATTER, 5), (ODOM, 3), (CHATTER, 6), (CHATTER, 7), (ODOM, 4), (CHATTER, 8)],
]


def _iso(moment: datetime) -> str:
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _batch_sealed(setup, batch: list[tuple[str, int]], first: int) -> list[bytes]:
    """The batch's envelopes as a paired agent seals them: one SM2 signature over the batch
    (provenance.sign_batch), each record's header carrying its topic_seq and batch place."""
    records = []
    for offset, (topic, number) in enumerate(batch):
        seq = first + offset
        header = {
            "owner": setup.owner.username,
            "robot": str(setup.robot.id),
            "topic": topic,
            "type": "std_msgs/String",
            "seq": seq,
            "time": _iso(T0 + timedelta(seconds=seq)),
            "topic_seq": number,
        }
        plaintext = json.dumps({"K": {"data": f"{topic} {number}"}}).encode()
        records.append((header, plaintext))
    headers = provenance.sign_batch(*setup.signing_key, records)
    return [
        envelope.seal(setup.key, header, plaintext)
        for header, (_, plaintext) in zip(headers, records, strict=True)
    ]


def _uploaded(setup, capture) -> dict[tuple[str, int], Record]:
    """Both batches uploaded as the robot (anchored inline), by (topic, topic_seq)."""
    uploaded = {}
    seq = 1
    for batch in BATCHES:
        with capture(execute=True):
            records = record_create_batch(
                robot=setup.robot, envelopes=_batch_sealed(setup, batch, seq)
            )
        for (topic, number), record in zip(batch, records, strict=True):
            Record.objects.filter(pk=record.pk).update(topic_seq=number)
            uploaded[topic, number] = record
        seq += len(batch)
    return uploaded


def _dropped(record: Record) -> None:
    """The record gone behind the portal's back: its row, its stored envelope, its cached
    copy."""
    envelope_storage().delete(record.storage_name)
    get_redis().delete(cache_key(record.id))
    Record.objects.filter(pk=record.pk).delete()


def _exported(setup, capture) -> tuple[bytes, bytes]:
    with capture(execute=True):
        export = export_create(requester=setup.owner)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    mcap, bundle = export_files(export)
    return bundle, mcap


@pytest.fixture
def counted_sm2(monkeypatch) -> dict[str, int]:
    """How many SM2 verifications run: the portal's check (sm2.verify_many, every core) and
    the verifier's (sm2.verify, one at a time)."""
    counts = {"many": 0, "one": 0}
    verify_many, verify_one = sm2.verify_many, sm2.verify

    def many(claims):
        counts["many"] += len(claims)
        return verify_many(claims)

    def one(*args, **kwargs):
        counts["one"] += 1
        return verify_one(*args, **kwargs)

    monkeypatch.setattr(sm2, "verify_many", many)
    monkeypatch.setattr(sm2, "verify", one)
    return counts


@pytest.fixture
def v2_export(make_paired_robot, django_capture_on_commit_callbacks, deployed, counted_sm2):
    setup = make_paired_robot("alice")
    uploaded = _uploaded(setup, django_capture_on_commit_callbacks)
    return setup, uploaded, deployed


def test_a_v2_export_verifies_with_one_sm2_per_batch_and_counts_every_record(
    v2_export, django_capture_on_commit_callbacks, chain_reader, counted_sm2
):
    setup, _uploaded_records, deployed = v2_export
    counted_sm2.update(many=0, one=0)
    bundle, mcap = _exported(setup, django_capture_on_commit_callbacks)
    assert counted_sm2["many"] == 2  # the export's check: one per batch, not one per record
    document = json.loads(bundle)
    assert document["format"] == BUNDLE_FORMAT
    entries = document["records"]
    assert len(entries) == 14
    for entry in entries:
        header = envelope.read_header(_envelope(entry)).header
        assert entry["topic_seq"] == header["topic_seq"]
        assert entry["batch"] == {
            "sig_index": header["sig_index"],
            "sig_size": 7,
            "sig_path": header["sig_path"],
        }
    assert document["streams"]["streams"] == [
        {
            "signer": setup.robot.key_hash,
            "topic": topic,
            "robot": str(setup.robot.id),
            "first": 0,
            "last": last,
            "count": last + 1,
            "gaps": [],
        }
        for topic, last in sorted([(CHATTER, 8), (ODOM, 4)])
    ]

    counted_sm2.update(many=0, one=0)
    report = export_verify(bundle, chain=chain_reader, mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    assert len(report.genuine) == 14
    assert counted_sm2["one"] == report.signatures_verified == 2  # one per batch
    assert [(s.topic, s.first, s.last, s.count, s.gaps) for s in report.streams] == [
        (CHATTER, 0, 8, 9, ()),
        (ODOM, 0, 4, 5, ()),
    ]

    # A record of a batch changed: its leaf no longer folds to the root the batch's signature
    # is over; only it fails, and the batch's signature is still verified once.
    changed = copy.deepcopy(document)
    entry = changed["records"][3]
    entry["plaintext"] = _base64(base64.b64decode(entry["plaintext"]).replace(b" 1", b" 9"))
    counted_sm2.update(one=0)
    report = export_verify(
        recomputed(changed, mcap)[0], chain=chain_reader, contract=deployed.address
    )
    assert [result.index for result in report.failed] == [3]
    assert "its robot signature does not hold" in report.failed[0].problems[0]

    # The bundle's topic_seq or batch differing from the envelope's: named.
    for name, value in (("topic_seq", 7), ("batch", None)):
        changed = copy.deepcopy(document)
        changed["records"][5][name] = value
        report = export_verify(
            recomputed(changed, mcap)[0], chain=chain_reader, contract=deployed.address
        )
        assert [result.index for result in report.failed] == [5], name
        assert name in report.failed[0].problems[0]

    # A bundle of the older format v2 (no topic_seq, batch or streams) still reads them: the
    # counting comes from the envelopes.
    old = copy.deepcopy(document)
    old["format"] = BUNDLE_FORMAT_V2
    del old["streams"]
    for entry in old["records"]:
        del entry["topic_seq"], entry["batch"]
    old["bundle_sm3"] = bundle_digest(old)
    report = export_verify(
        bundle_serialise(old), chain=chain_reader, mcap=mcap, contract=deployed.address
    )
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    assert [(s.first, s.last, s.count, s.gaps) for s in report.streams] == [
        (0, 8, 9, ()),
        (0, 4, 5, ()),
    ]

    # The same record twice in the bundle (its MCAP message too): the number is counted once.
    twice = copy.deepcopy(document)
    copied = copy.deepcopy(twice["records"][0])
    copied["mcap"]["sequence"] = 15
    twice["records"].append(copied)
    report = export_verify(recomputed(twice, mcap)[0], chain=chain_reader)
    assert [result.index for result in report.failed] == [14]
    assert "carries the same topic_seq 0" in report.failed[0].problems[0]


@pytest.mark.process
def test_gaps_are_named_missing_deleted_and_retention_and_complete_fails_on_them(
    v2_export, django_capture_on_commit_callbacks, chain_reader, isolated_portal, tmp_path
):
    setup, uploaded, deployed = v2_export
    # Retention: the robot keeps a day; the sweep runs a day after the third record.
    setup.robot.retention_days = 1
    setup.robot.save(update_fields=["retention_days"])
    with django_capture_on_commit_callbacks(execute=True):
        retention_apply(now=T0 + timedelta(days=1, seconds=4))
    assert set(
        Record.objects.filter(deletion_reason=Record.Deletion.RETENTION).values_list(
            "topic", "topic_seq"
        )
    ) == {(CHATTER, 0), (ODOM, 0), (CHATTER, 1)}
    # The owner deletes one; one is dropped behind the portal's back.
    with django_capture_on_commit_callbacks(execute=True):
        record_delete(owner=setup.owner, record_id=uploaded[CHATTER, 4].pk, actor=setup.owner.user)
    _dropped(uploaded[CHATTER, 6])
    bundle, mcap = _exported(setup, django_capture_on_commit_callbacks)

    report = export_verify(bundle, chain=chain_reader, mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    chatter, odom = report.streams
    assert (chatter.topic, chatter.first, chatter.last, chatter.count) == (CHATTER, 2, 8, 5)
    assert [(g.start, g.end, g.reason) for g in chatter.gaps] == [
        (0, 1, "retention"),
        (4, 4, "deleted"),
        (6, 6, "missing"),
    ]
    assert chatter.gaps[1].detail.startswith("at 20")
    assert [(g.start, g.end, g.reason) for g in odom.gaps] == [(0, 0, "retention")]

    # The gaps come from the verified records' signed numbers, not from the bundle's claim: a
    # bundle whose streams say nothing is missing still has the gap, named `missing`.
    document = json.loads(bundle)
    silent = copy.deepcopy(document)
    for stream in silent["streams"]["streams"]:
        stream["gaps"] = []
        stream["first"] = 2 if stream["topic"] == CHATTER else 1
    forged, _ = recomputed(silent, mcap)
    report = export_verify(forged, chain=chain_reader, mcap=mcap, contract=deployed.address)
    assert report.ok
    assert [(g.start, g.end, g.reason) for g in report.streams[0].gaps] == [
        (4, 4, "missing"),
        (6, 6, "missing"),
    ]
    # A portal that calls the dropped record deleted is believed about the reason only:
    # `--complete` fails on any gap, whatever its reason.
    excused = copy.deepcopy(document)
    excused["streams"]["streams"][0]["gaps"][2]["reason"] = "deleted"
    excused_bundle, _ = recomputed(excused, mcap)

    # As an auditor runs it: the real command, in a process of its own.
    files = {}
    for name, data in (
        ("proofs.json", bundle),
        ("export.mcap", mcap),
        ("excused.json", excused_bundle),
    ):
        files[name] = tmp_path / name
        files[name].write_bytes(data)

    def run(bundle_file: Path, *flags: str) -> subprocess.CompletedProcess:
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "authros_verify",
                str(bundle_file),
                *("--mcap", str(files["export.mcap"])),
                *("--rpc", isolated_portal, "--contract", deployed.address),
                *flags,
            ],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )

    plain = run(files["proofs.json"])
    assert plain.returncode == 0, plain.stdout + plain.stderr
    assert "9 of 9 records verified against the chain: 9 genuine" in plain.stdout
    assert "2 SM2 verifications" in plain.stdout
    assert f"topic {CHATTER} (robot {setup.robot.id}): topic_seq 2..8, 5 records, 3 gaps" in (
        plain.stdout
    )
    assert "    GAP 0..1 (2 records): retention (at 20" in plain.stdout
    assert "    GAP 4 (1 records): deleted (at 20" in plain.stdout
    assert "    GAP 6 (1 records): missing\n" in plain.stdout
    assert plain.stdout.rstrip().splitlines()[-1].startswith("VERIFIED: ")

    complete = run(files["proofs.json"], "--complete")
    assert complete.returncode == 1, complete.stdout + complete.stderr
    assert "    GAP 6 (1 records): missing" in complete.stdout
    assert "FAILED: 4 gaps, 0 records no stream counts (--complete)" in complete.stdout

    excused_run = run(files["excused.json"], "--complete")
    assert excused_run.returncode == 1
    assert "    GAP 6 (1 records): deleted" in excused_run.stdout


def test_a_complete_export_passes_complete(
    v2_export, django_capture_on_commit_callbacks, deployed, tmp_path, capsys, isolated_portal
):
    setup, _uploaded_records, deployed = v2_export
    bundle, mcap = _exported(setup, django_capture_on_commit_callbacks)
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)
    arguments = [
        str(tmp_path / "proofs.json"),
        *("--mcap", str(tmp_path / "export.mcap")),
        *("--rpc", isolated_portal, "--contract", deployed.address, "--complete"),
    ]
    assert main(arguments) == 0
    out = capsys.readouterr().out
    assert f"topic {CHATTER} (robot {setup.robot.id}): topic_seq 0..8, 9 records, nothing" in out


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4])
def test_an_mcap_file_of_compressed_chunks_is_read_and_a_change_in_one_named(
    v2_export, django_capture_on_commit_callbacks, chain_reader, compression
):
    setup, _uploaded_records, deployed = v2_export
    bundle, mcap = _exported(setup, django_capture_on_commit_callbacks)
    document = json.loads(bundle)
    compressed = _rewritten(mcap, compression)
    assert compressed != mcap
    assert {chunk.compression for chunk in _chunks(compressed)} == {compression.name.lower()}
    again = copy.deepcopy(document)
    again["mcap"] = {**again["mcap"], "size": len(compressed), "sm3": "0x" + sm3_hex(compressed)}
    again["bundle_sm3"] = bundle_digest(again)
    report = export_verify(
        bundle_serialise(again), chain=chain_reader, mcap=compressed, contract=deployed.address
    )
    assert report.ok, (report.problems, [r.problems for r in report.failed])

    # One message changed inside a compressed chunk, every SM3 recomputed: its record named.
    entry = document["records"][2]
    sequence = entry["mcap"]["sequence"]
    forged_mcap = _rewritten(mcap, compression, change={sequence: b"changed"})
    changed = copy.deepcopy(document)
    changed["records"][2]["mcap"]["sm3"] = "0x" + sm3_hex(_message_data(forged_mcap, sequence))
    changed["mcap"] = {
        **changed["mcap"],
        "size": len(forged_mcap),
        "sm3": "0x" + sm3_hex(forged_mcap),
    }
    changed["bundle_sm3"] = bundle_digest(changed)
    report = export_verify(
        bundle_serialise(changed), chain=chain_reader, mcap=forged_mcap, contract=deployed.address
    )
    assert [result.index for result in report.failed] == [2]
    assert report.problems == []


def _rewritten(
    mcap: bytes, compression: CompressionType, *, change: dict[int, bytes] | None = None
) -> bytes:
    """The file written again with the `mcap` library, its chunks compressed, small chunks so
    that there are several; the given messages' data with bytes appended."""
    messages = {
        sequence: _message_data(mcap, sequence) + appended
        for sequence, appended in (change or {}).items()
    }
    return mcap_rewritten(mcap, messages=messages, compression=compression, chunk_size=256)


def _chunks(mcap: bytes) -> list[Chunk]:
    return [
        record
        for record in StreamReader(io.BytesIO(mcap), emit_chunks=True).records
        if isinstance(record, Chunk)
    ]


def _message_data(mcap: bytes, sequence: int) -> bytes:
    reader = make_reader(io.BytesIO(mcap))
    return next(
        message.data
        for _schema, _channel, message in reader.iter_messages()
        if message.sequence == sequence
    )


def _envelope(entry: dict) -> bytes:
    return base64.b64decode(entry["envelope"])


def _base64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def test_a_record_the_export_left_out_is_an_excluded_gap_and_bad_streams_are_named(
    v2_export, django_capture_on_commit_callbacks, chain_reader
):
    setup, uploaded, deployed = v2_export
    tamper(uploaded[ODOM, 2])  # its stored envelope changed: the export leaves it out
    bundle, mcap = _exported(setup, django_capture_on_commit_callbacks)
    document = json.loads(bundle)
    (left_out,) = document["excluded"]
    assert (left_out["reason"], left_out["signer"], left_out["topic_seq"]) == (
        "integrity_check_failed",
        setup.robot.key_hash,
        2,
    )
    report = export_verify(bundle, chain=chain_reader, mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    odom = report.streams[1]
    assert [(g.start, g.end, g.reason) for g in odom.gaps] == [(2, 2, "excluded")]
    assert odom.gaps[0].detail == f"integrity_check_failed: record {uploaded[ODOM, 2].pk}"

    # The portal's streams not of their form: a problem of the bundle, the gaps still counted.
    for broken in (
        {"streams": [], "uncounted": -1},
        {"streams": [{"signer": "x"}], "uncounted": 0},
        {
            "streams": [
                {**document["streams"]["streams"][0], "gaps": [{"from": 3, "to": 2, "reason": "x"}]}
            ],
            "uncounted": 0,
        },
    ):
        changed = copy.deepcopy(document)
        changed["streams"] = broken
        report = export_verify(recomputed(changed, mcap)[0], chain=chain_reader)
        assert len(report.problems) == 1, broken
        assert report.problems[0].startswith("the bundle's streams"), report.problems
        assert [(g.start, g.reason) for g in report.streams[1].gaps] == [(2, "missing")]

    # A portal claiming a billion numbers past the last costs nothing: one gap, `missing`.
    claimed = copy.deepcopy(document)
    claimed["streams"]["streams"][0]["last"] = 10**9
    report = export_verify(recomputed(claimed, mcap)[0], chain=chain_reader)
    assert [(g.start, g.end, g.reason) for g in report.streams[0].gaps] == [(9, 10**9, "missing")]
