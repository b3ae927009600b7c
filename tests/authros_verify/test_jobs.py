"""Issue 45: the verifier's records checked by forked processes (`--jobs N`) give the same
report as one process, on a good export and on tampered ones; and what the check keeps per
record stays small, so that its memory does not follow the bundle's size.

The export is a paired robot's records signed one upload batch at a time (provenance v2),
exported through the real exporter; the chunks handed to each process are made small, so that
an export of a few batches is cut into several (at the batches' edges: each batch's signature
is still verified once).
"""

import base64
import copy
import json
import tracemalloc
from datetime import UTC, datetime, timedelta

import pytest

from authros_verify import check
from authros_verify import verify as export_verify
from authros_verify.__main__ import main
from sharing.exports.create import export_create
from sharing.models import Export
from sharing.services.uploads import record_create_batch
from smcrypto import envelope, provenance
from tests.authros_verify.conftest import export_files, export_of, recomputed
from tests.support.batches import seal_batch

pytestmark = pytest.mark.django_db

BATCHES, BATCH = 6, 5  # six upload batches of five records


@pytest.fixture
def batched(make_paired_robot, django_capture_on_commit_callbacks, deployed, monkeypatch):
    """(bundle, mcap, deployed) of an export of six v2 batches, checked four lines a chunk."""
    monkeypatch.setattr(check, "CHUNK_LINES", 4)
    setup = make_paired_robot("alice")
    envelopes = []
    for batch in range(BATCHES):
        envelopes += seal_batch(setup, range(batch * BATCH + 1, (batch + 1) * BATCH + 1))
    bundle, mcap = export_of(setup, django_capture_on_commit_callbacks, envelopes)
    return bundle, mcap, deployed


def _summary(report: check.Report) -> tuple:
    """Everything a report says: its verdict, problems, every record's result, its streams
    and the SM2 verifications it made."""
    return (
        report.ok,
        report.problems,
        [(r.index, r.record, r.problems, r.signed, r.topic_seq) for r in report.records],
        report.streams,
        report.signatures_verified,
    )


def _both(bundle: bytes, mcap: bytes, chain_reader, deployed) -> tuple[tuple, tuple]:
    one, two = (
        export_verify(bundle, chain=chain_reader, mcap=mcap, contract=deployed.address, jobs=jobs)
        for jobs in (1, 2)
    )
    return _summary(one), _summary(two)


def test_jobs_give_one_process_report_on_a_good_export(batched, chain_reader):
    bundle, mcap, deployed = batched
    one, two = _both(bundle, mcap, chain_reader, deployed)
    assert one == two
    ok, problems, records, streams, verified = two
    assert ok
    assert problems == []
    assert len(records) == BATCHES * BATCH
    assert all(signed for _i, _r, _p, signed, _n in records)
    assert verified == BATCHES  # one SM2 verification per batch, though cut into chunks
    assert [(s.first, s.last, s.count, s.gaps) for s in streams] == [(1, 30, 30, ())]


def test_jobs_give_one_process_report_on_tampered_exports(batched, chain_reader):
    bundle, mcap, deployed = batched
    document = json.loads(bundle)

    # A plaintext changed (every SM3 and bundle_sm3 recomputed): its batch's signature does
    # not hold over it; only that record fails.
    changed = copy.deepcopy(document)
    plaintext = bytearray(base64.b64decode(changed["records"][7]["plaintext"]))
    plaintext[-2] ^= 1
    changed["records"][7]["plaintext"] = base64.b64encode(bytes(plaintext)).decode()
    # An MCAP message changed, its SM3 in the bundle recomputed.
    message = copy.deepcopy(document)
    sequence = message["records"][12]["mcap"]["sequence"]
    # A record dropped from the bundle: its stream names the gap missing.
    dropped = copy.deepcopy(document)
    del dropped["records"][20]
    cases = {
        "plaintext": recomputed(changed, mcap),
        "message": recomputed(message, mcap, messages={sequence: b"\x00\x01\x00\x00changed"}),
        "dropped": recomputed(dropped, mcap),
        # A byte of a line changed: not in its canonical form, so read whole (one process).
        "line": (bundle.replace(b'"seq":9,', b'"seq": 9,', 1), mcap),
        "digest": (bundle.replace(document["bundle_sm3"][2:6].encode(), b"0000", 1), mcap),
    }
    for name, (forged, forged_mcap) in cases.items():
        one, two = _both(forged, forged_mcap, chain_reader, deployed)
        assert one == two, name
        ok, _problems, records, _streams, _verified = two
        assert not ok, name
        failed = [index for index, _r, record_problems, _s, _n in records if record_problems]
        expected = {"plaintext": [7], "message": [12], "dropped": [], "line": [8], "digest": []}
        assert failed == expected[name], (name, records)
    assert "missing" in [
        gap.reason for gap in _both(*cases["dropped"], chain_reader, deployed)[1][3][0].gaps
    ]


def test_the_command_with_jobs_checks_over_http(batched, tmp_path, capsys, isolated_portal):
    bundle, mcap, deployed = batched
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)
    arguments = [
        str(tmp_path / "proofs.json"),
        *("--mcap", str(tmp_path / "export.mcap")),
        *("--rpc", isolated_portal, "--contract", deployed.address, "--complete"),
    ]
    for jobs in ("1", "2"):
        assert main([*arguments, "--jobs", jobs]) == 0
        out = capsys.readouterr().out
        assert "30 of 30 records verified against the chain: 30 genuine" in out
        assert f"{BATCHES} SM2 verifications" in out
        assert out.rstrip().splitlines()[-1].startswith("VERIFIED: 30 records, 0 refused, chain ")


T0 = datetime(2026, 5, 1, tzinfo=UTC)


def test_what_the_check_keeps_per_record_stays_small(
    make_paired_robot, django_capture_on_commit_callbacks, chain_reader, deployed, tmp_path
):
    """The verifier's peak memory (tracemalloc) on 8,000 records against 2,000 of the same
    export: under 2 KiB more per record, where each record's line of the bundle alone is
    larger (a verifier that held the bundle, or each record's entry, would exceed it)."""
    setup = make_paired_robot("alice")
    total, batch = 8_000, 500
    for first in range(0, total, batch):
        records = [
            (
                {
                    "owner": setup.owner.username,
                    "robot": str(setup.robot.id),
                    "topic": "/chatter",
                    "type": "std_msgs/String",
                    "seq": seq + 1,
                    "time": (T0 + timedelta(seconds=seq)).isoformat().replace("+00:00", "Z"),
                    "topic_seq": seq,
                },
                json.dumps({"K": {"data": f"message {seq} " + "x" * 200}}).encode(),
            )
            for seq in range(first, first + batch)
        ]
        headers = provenance.sign_batch(*setup.signing_key, records)
        envelopes = [
            envelope.seal(setup.key, header, body)
            for header, (_, body) in zip(headers, records, strict=True)
        ]
        with django_capture_on_commit_callbacks(execute=True):
            record_create_batch(robot=setup.robot, envelopes=envelopes)
    peaks, lines = {}, {}
    for count in (2_000, total):
        with django_capture_on_commit_callbacks(execute=True):
            export = export_create(requester=setup.owner, until=T0 + timedelta(seconds=count))
        export.refresh_from_db()
        assert (export.status, export.exported) == (Export.Status.DONE, count), export.error
        mcap, bundle = export_files(export)
        (tmp_path / "proofs.json").write_bytes(bundle)
        (tmp_path / "export.mcap").write_bytes(mcap)
        lines[count] = len(bundle) / count
        del mcap, bundle
        tracemalloc.start()
        try:
            report = export_verify(
                tmp_path / "proofs.json",
                chain=chain_reader,
                mcap=tmp_path / "export.mcap",
                contract=deployed.address,
            )
            peaks[count] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert report.ok, report.problems
        assert len(report.records) == count
    # Measured: about 730 bytes more per record (its result, its MCAP message's SM3 and
    # place); a record's line is over 4 KiB, which a verifier holding them would keep.
    assert min(lines.values()) > 4096
    assert (peaks[total] - peaks[2_000]) / (total - 2_000) < 2048, peaks
