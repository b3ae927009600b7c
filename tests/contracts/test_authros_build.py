"""The committed artifact is fresh, reproducible and exposes the fixed interface."""

import hashlib
import json
import shutil
import subprocess

import pytest
from eth_utils import abi_to_signature, keccak

from tests.contracts.conftest import ARTIFACT_PATH, REPO_ROOT

SOURCE = REPO_ROOT / "contracts" / "AuthROS.sol"
BUILD_SCRIPT = REPO_ROOT / "contracts" / "build.mjs"
NODE = shutil.which("node")
needs_node = pytest.mark.skipif(NODE is None, reason="node is not installed")

# The fixed interface of DESIGN.md "Contract", plus the views we added. Renames break callers.
FUNCTIONS = {
    "MAX_BATCH()",
    "admin()",
    "anchorRoot(bytes32,uint64,bytes32)",
    "authorityGrant(address)",
    "authorityGrantScoped(address,bytes32,uint64)",
    "authorityRevoke(address)",
    "commitmentOf(address)",
    "dataCheck(bytes32,bytes32)",
    "dataCheckOf(address,bytes32,bytes32)",
    "dataQuery(bytes32)",
    "dataQueryOf(address,bytes32)",
    "dataUpload(bytes32,bytes32,uint64,bytes32)",
    "dataUploadBatch(bytes32[],bytes32[],uint64[],bytes32[])",
    "enroll(address)",
    "grantOf(address,address)",
    "hasAccess(address,address)",
    "isEnrolled(address)",
    "isRegistered(address)",
    "lastRootOf(address)",
    "recordCount()",
    "register(bytes32)",
    "robotKeyAdd(bytes32,bytes)",
    "robotKeyOf(bytes32)",
    "robotKeyOfOwner(address,bytes32)",
    "robotKeyRevoke(bytes32)",
    "rootOf(address,bytes32)",
    "rotateKey(bytes32)",
}
EVENTS = {
    "AuthorityGranted(address,address)",
    "AuthorityRevoked(address,address)",
    "AuthorityScoped(address,address,bytes32,uint64)",
    "DataUploaded(bytes32,address,bytes32,uint64,bytes32)",
    "Enrolled(address)",
    "KeyRotated(address,bytes32,bytes32)",
    "Registered(address,bytes32)",
    "RobotKeyAdded(address,bytes32,bytes)",
    "RobotKeyRevoked(address,bytes32)",
    "RootAnchored(address,bytes32,uint64,bytes32,uint64)",
}


def start_build_check(cwd):
    return subprocess.Popen(
        [NODE, "contracts/build.mjs", "--check"],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.process
@needs_node
def test_build_check_accepts_the_committed_artifact_and_refuses_a_stale_one(tmp_path):
    (tmp_path / "contracts" / "build").mkdir(parents=True)
    shutil.copy(SOURCE, tmp_path / "contracts" / "AuthROS.sol")
    shutil.copy(BUILD_SCRIPT, tmp_path / "contracts" / "build.mjs")
    (tmp_path / "node_modules").symlink_to(REPO_ROOT / "node_modules")
    stale = json.loads(ARTIFACT_PATH.read_text())
    stale["bytecode"] = stale["bytecode"][:-2] + "00"
    (tmp_path / "contracts" / "build" / "AuthROS.json").write_text(json.dumps(stale))

    # Both compile (seconds each with solcjs): run them side by side.
    committed, tampered = start_build_check(REPO_ROOT), start_build_check(tmp_path)
    try:
        committed_out, committed_err = committed.communicate(timeout=120)
        _, tampered_err = tampered.communicate(timeout=120)
    finally:
        for process in (committed, tampered):
            process.kill()  # no-op once exited; stops a hung compile on timeout

    assert committed.returncode == 0, committed_err + committed_out
    assert tampered.returncode == 1
    assert "contracts/build/AuthROS.json is stale" in tampered_err


def test_artifact_names_the_current_source(artifact):
    source = SOURCE.read_bytes()
    assert artifact["source"] == {
        "path": "contracts/AuthROS.sol",
        "keccak256": "0x" + keccak(source).hex(),
        "sha256": "0x" + hashlib.sha256(source).hexdigest(),
    }


def test_artifact_is_pinned_and_reproducible(artifact):
    assert artifact["contractName"] == "AuthROS"
    assert artifact["compiler"]["version"].startswith("0.8.30+")
    assert artifact["compiler"]["evmVersion"] == "paris"
    assert artifact["compiler"]["optimizer"] == {"enabled": True, "runs": 200}
    # bytecodeHash "none": the CBOR trailer holds only {"solc": 0.8.30}, no metadata hash.
    solc_only_trailer = "a164736f6c6343" + "00081e" + "000a"
    assert artifact["deployedBytecode"].endswith(solc_only_trailer)
    assert artifact["bytecode"].startswith("0x")
    text = ARTIFACT_PATH.read_text()
    assert text == json.dumps(json.loads(text), indent=2, sort_keys=True) + "\n"


def test_abi_is_the_fixed_interface(artifact):
    signatures = {kind: set() for kind in ("function", "event", "error")}
    for entry in artifact["abi"]:
        if entry["type"] in signatures:
            signatures[entry["type"]].add(abi_to_signature(entry))
    assert signatures["function"] == FUNCTIONS
    assert signatures["event"] == EVENTS
    # + ExpiryInPast, SameTerms (scoped grants); + six refusals of robot keys.
    assert len(signatures["error"]) == 30
