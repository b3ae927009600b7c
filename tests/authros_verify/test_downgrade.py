"""A bundle relabelled to an older format cannot make a signed record pass as unsigned: whether
a record is signed is read from its anchored envelope's header, whose SM3 the chain anchors,
never from the bundle's labels (the audit finding of issue 44). Against the session's anvil,
on an export made by the portal's own services, forged as a tamperer would forge it (every
SM3, size and digest recomputed)."""

import copy
import json

import pytest

from authros_verify import BUNDLE_FORMAT_V1, verify
from authros_verify.__main__ import main
from authros_verify.check import RECORD_FIELDS_V1
from authros_verify.mcapfile import mcap_messages
from tests.authros_verify.conftest import export_of, recomputed

pytestmark = pytest.mark.django_db


def _reading(seq: int) -> bytes:
    return json.dumps({"K": {"data": f"reading {seq}"}, "Type": "std_msgs/String"}).encode()


def test_a_signed_record_relabelled_v1_with_its_message_changed_fails(
    make_paired_robot,
    django_capture_on_commit_callbacks,
    deployed,
    isolated_portal,
    tmp_path,
    capsys,
):
    setup = make_paired_robot("alice")
    envelopes = [
        setup.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            time=f"2026-05-01T12:00:0{seq}.000001Z",
            plaintext=_reading(seq),
        )
        for seq in (1, 2)
    ]
    bundle, mcap = export_of(setup, django_capture_on_commit_callbacks, envelopes)
    document = json.loads(bundle)
    target = document["records"][0]
    sequence = target["mcap"]["sequence"]
    original = next(m for m in mcap_messages(mcap) if m.sequence == sequence).data
    assert original.count(b"reading 1") == 1
    changed = original.replace(b"reading 1", b"reading 9")

    # The attack: the format relabelled to v1 (which carries no signatures), the signature and
    # the plaintext dropped, the message changed, every SM3, size and digest recomputed.
    forged = copy.deepcopy(document)
    forged["format"] = BUNDLE_FORMAT_V1
    for entry in forged["records"]:
        for name in set(entry) - RECORD_FIELDS_V1:
            del entry[name]
    forged_bundle, forged_mcap = recomputed(forged, mcap, messages={sequence: changed})
    assert forged_mcap != mcap

    report = verify(forged_bundle, chain=_reader(deployed), mcap=forged_mcap)
    assert not report.ok
    failed = {result.index: "; ".join(result.problems) for result in report.failed}
    assert sorted(failed) == [0, 1], failed  # both are signed; neither can pass unsigned
    assert "its anchored envelope is signed by robot key" in failed[0]
    assert report.not_genuine == []

    (tmp_path / "proofs.json").write_bytes(forged_bundle)
    (tmp_path / "export.mcap").write_bytes(forged_mcap)
    arguments = [
        str(tmp_path / "proofs.json"),
        *("--mcap", str(tmp_path / "export.mcap")),
        *("--rpc", isolated_portal, "--contract", deployed.address),
    ]
    assert main(arguments) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out
    assert "UNSIGNED" not in out


def _reader(deployed):
    from authros_verify import ChainReader

    return ChainReader(deployed.w3)
