"""authros_verify, the standalone check of an export: the good bundle passes against the chain
the portal anchored on; one changed byte anywhere in the bundle or the MCAP file fails it, and
a changed byte in a record's line or message names that record.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from authros_verify import ChainReader, check, record_line_index, verify
from authros_verify.__main__ import main
from authros_verify.abi import ABI
from chainworker import services as chain_services
from chainworker.codec import ContractArtifact
from stack.anvil import start_anvil
from tests.authros_verify.conftest import export_of
from tests.support.harness import REPO_ROOT

pytestmark = pytest.mark.django_db


def _export(setup, capture, count: int = 2) -> tuple[bytes, bytes]:
    """A small export of `count` std_msgs/String records of one owner: (bundle, mcap)."""
    envelopes = [
        setup.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            time=f"2026-05-01T12:00:0{seq}.000001Z",
            plaintext=json.dumps({"K": {"data": f"msg {seq}"}}).encode(),
        )
        for seq in range(1, count + 1)
    ]
    return export_of(setup, capture, envelopes)


def _flipped(data: bytes, position: int, mask: int = 0x01) -> bytes:
    return data[:position] + bytes([data[position] ^ mask]) + data[position + 1 :]


@pytest.fixture
def small_export(make_robot, django_capture_on_commit_callbacks, deployed):
    bundle, mcap = _export(make_robot("alice"), django_capture_on_commit_callbacks)
    # One reader for the whole test: the chain's answers do not change, each is asked once.
    return bundle, mcap, ChainReader(deployed.w3), deployed.address


def _record_ids(bundle: bytes) -> list[str]:
    return [entry["record"] for entry in json.loads(bundle)["records"]]


def _assert_caught(report, bundle: bytes, position: int, ids: list[str]) -> None:
    assert not report.ok, position
    index = record_line_index(bundle, position, len(ids))
    if index is not None:  # the byte is in a record's line: that record, and only it, is named
        named = [(result.index, result.record) for result in report.failed]
        assert [i for i, _ in named] == [index], (position, named, report.problems)


def test_one_changed_byte_anywhere_in_the_bundle_or_mcap_is_caught_and_named(small_export):
    bundle, mcap, chain, contract = small_export
    good = verify(bundle, chain=chain, mcap=mcap, contract=contract)
    assert good.ok, (good.problems, [r.problems for r in good.failed])
    ids = _record_ids(bundle)
    assert [result.record for result in good.records] == ids
    for position in range(len(bundle)):
        report = verify(_flipped(bundle, position), chain=chain, mcap=mcap, contract=contract)
        _assert_caught(report, bundle, position, ids)

    @settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
    @given(position=st.integers(0, len(bundle) - 1), value=st.integers(0, 255))
    def any_value(position: int, value: int) -> None:
        if bundle[position] == value:
            return
        changed = bundle[:position] + bytes([value]) + bundle[position + 1 :]
        report = verify(changed, chain=chain, mcap=mcap, contract=contract)
        _assert_caught(report, bundle, position, ids)

    any_value()

    # What the random search found: a byte turned into a line break or a space (a comma, a
    # quote, a brace) breaks the JSON on another line, or makes a field appear twice; the
    # record whose line held it is still the one named.
    for value in b"\n ,":
        for position in range(len(bundle)):
            if bundle[position] != value:
                changed = bundle[:position] + bytes([value]) + bundle[position + 1 :]
                report = verify(changed, chain=chain, mcap=mcap, contract=contract)
                _assert_caught(report, bundle, position, ids)

    # A digit changed to "e" makes a fraction, beyond any float ("1e999" is infinite): caught
    # and named like any other change, not a crash of the verifier.
    for field in (b'"chain_id":', b'"block":'):
        position = bundle.index(field) + len(field)
        changed = bundle[:position] + b"1e999" + bundle[position + 1 :]
        _assert_caught(
            verify(changed, chain=chain, mcap=mcap, contract=contract), bundle, position, ids
        )

    entries = json.loads(bundle)["records"]
    for position in range(len(mcap)):
        report = verify(bundle, chain=chain, mcap=_flipped(mcap, position), contract=contract)
        assert not report.ok, position
    # A byte of a message's data names its record.
    for entry in entries:
        data = f"msg {entry['seq']}".encode()
        position = mcap.index(data)
        report = verify(bundle, chain=chain, mcap=_flipped(mcap, position), contract=contract)
        assert [result.record for result in report.failed] == [entry["record"]]

    # Another contract or chain than the one the verifier expects.
    other = "0x" + "11" * 20
    report = verify(bundle, chain=chain, mcap=mcap, contract=other)
    assert not report.ok
    assert any("not the expected" in problem for problem in report.problems)
    assert not verify(bundle, chain=chain, chain_id=1).ok


def test_the_abi_the_verifier_carries_is_the_contracts():
    artifact = {entry.get("name"): entry for entry in ContractArtifact.load().abi}
    for entry in ABI:
        assert artifact[entry["name"]] == entry


# `python -m authros_verify ARGS`, then a check that the run loaded neither Django nor the portal.
RUN_AND_CHECK_MODULES = """
import runpy, sys
sys.argv[0] = "authros_verify"
try:
    runpy.run_module("authros_verify", run_name="__main__", alter_sys=True)
except SystemExit as exit:
    loaded = {name.split(".")[0] for name in sys.modules}
    forbidden = {"django", "rest_framework", "celery", "kombu", "portal", "accounts", "sharing",
                 "chainworker", "core", "ros_agent"}
    assert not loaded & forbidden, sorted(loaded & forbidden)
    raise
"""


@pytest.fixture
def on_anvil(settings, isolated_portal):
    """The portal's chain is a real anvil node."""
    with start_anvil(zero_gas=True) as node:
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()
        yield node
        chain_services._clients.clear()


@pytest.mark.process
def test_the_command_checks_a_record_mode_export_against_anvil(
    on_anvil, records_mode, make_robot, django_capture_on_commit_callbacks, tmp_path: Path, capsys
):
    bundle, mcap = _export(make_robot("alice"), django_capture_on_commit_callbacks)
    contract = chain_services.chain_client().address
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)

    passed = subprocess.run(
        [
            sys.executable,
            *("-c", RUN_AND_CHECK_MODULES, str(tmp_path / "proofs.json")),
            *("--mcap", str(tmp_path / "export.mcap"), "--rpc", on_anvil.url),
            *("--contract", contract),
        ],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        timeout=120,
        check=False,
    )
    assert passed.returncode == 0, passed.stdout + passed.stderr
    assert "2 of 2 records verified" in passed.stdout
    # The same command in this process: a changed message names its record, and a node
    # that cannot be reached is exit status 2.
    entry = json.loads(bundle)["records"][1]
    (tmp_path / "export.mcap").write_bytes(_flipped(mcap, mcap.index(b"msg 2")))
    arguments = [str(tmp_path / "proofs.json"), "--mcap", str(tmp_path / "export.mcap")]
    assert main([*arguments, "--rpc", on_anvil.url, "--contract", contract]) == 1
    assert f"FAIL record {entry['record']}" in capsys.readouterr().out
    assert main([*arguments, "--rpc", "http://127.0.0.1:9"]) == 2


def test_a_bundle_in_its_canonical_form_is_read_line_by_line_and_one_that_is_not_whole(
    small_export, tmp_path, monkeypatch
):
    """The bundle as the portal writes it is checked from its file a line at a time, never
    held whole; a bundle whose form is broken is read whole, to name the line that changed."""
    bundle, mcap, chain, contract = small_export
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)
    whole = check._verify_whole
    read_whole = []

    def spy(data, **kwargs):
        read_whole.append(len(data))
        return whole(data, **kwargs)

    monkeypatch.setattr(check, "_verify_whole", spy)
    report = verify(
        tmp_path / "proofs.json", chain=chain, mcap=tmp_path / "export.mcap", contract=contract
    )
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    assert [result.record for result in report.records] == _record_ids(bundle)
    assert read_whole == []

    # Its digest changed (the form still holds): caught line by line.
    position = bundle.index(b'"bundle_sm3":"0x') + len(b'"bundle_sm3":"0x')
    changed = _flipped(bundle, position, 0x03)
    report = verify(changed, chain=chain, mcap=mcap, contract=contract)
    assert report.problems == ["the bundle's digest (bundle_sm3) does not match its content"]
    assert read_whole == []

    # A space in the second record's line: read whole, that record named.
    second = bundle.index(b"\n", bundle.index(b"\n{") + 1)
    position = bundle.index(b'"anchor":', second) + len(b'"anchor":')
    changed = bundle[:position] + b" " + bundle[position:]
    report = verify(changed, chain=chain, mcap=mcap, contract=contract)
    assert [result.index for result in report.failed] == [1]
    assert read_whole == [len(changed)]

    # No line break at the end: not its form either.
    report = verify(bundle[:-1], chain=chain, mcap=mcap, contract=contract)
    assert not report.ok
    assert len(read_whole) == 2
