"""`authros_verify record`: one record as the portal serves it to its owner or a grantee,
checked against the caller's own key and the chain. A genuine record holds for both; every
way a portal could lie (other content, another record's proof, a path, a block, a key, a
record forged with the owner's key and EOA) fails, naming its check."""

import base64
import copy
import json
import uuid
from pathlib import Path

import pytest

from accounts.selectors import owner_eoa_account
from authros_verify import ChainReader, record_check
from authros_verify.__main__ import main
from sharing.services.grants import grant_create
from sharing.services.uploads import record_create_batch
from smcrypto import envelope, provenance, sm2, sm4
from tests.api.conftest import token_client
from tests.authros_verify.conftest import forged_proof
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db

RECORDS = "/api/v1/records/"


def _plaintext(seq: int) -> bytes:
    return json.dumps({"K": {"data": f"reading {seq}"}, "Type": "std_msgs/String"}).encode()


@pytest.fixture
def shared(make_paired_robot, make_owner, make_owner_token, django_capture_on_commit_callbacks):
    """alice's paired robot's two signed records, anchored in one tree; bob, with his own key,
    has a grant from alice. Owner API tokens (`read`) for both."""
    alice = make_paired_robot("alice")
    bob_key = sm4.generate_key()
    bob = make_owner("bob", key=bob_key)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    envelopes = [
        alice.seal(seq, topic="/chatter", data_type="std_msgs/String", plaintext=_plaintext(seq))
        for seq in (1, 2)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=alice.robot, envelopes=envelopes)
    return {
        "alice": alice,
        "records": [str(record.pk) for record in records],
        "viewers": {
            "alice": (alice.key, make_owner_token(alice.owner, scopes=("read",))[1]),
            "bob": (bob_key, make_owner_token(bob, scopes=("read",))[1]),
        },
    }


def _answers(token: str, record: str) -> tuple[dict, dict]:
    """The portal's (content, proof) answers, as the command fetches them."""
    api = token_client(token)
    proof, content = api.get(f"{RECORDS}{record}/proof/"), api.get(f"{RECORDS}{record}/content/")
    assert (proof.status_code, content.status_code) == (200, 200), (proof.json(), content.json())
    return content.json(), proof.json()


def _failed(checked) -> list[str]:
    return [outcome.check for outcome in checked.failed]


@pytest.mark.django_db(transaction=True)
def test_the_command_prints_a_genuine_record_for_owner_and_grantee(
    live_server, shared, deployed, isolated_portal, tmp_path: Path, capsysbinary
):
    """Through a real HTTP server, as an owner or a grantee runs it."""
    record = shared["records"][0]
    for name, (key, token) in shared["viewers"].items():
        key_file, token_file = tmp_path / f"{name}.sm4", tmp_path / f"{name}.token"
        key_file.write_text(key.hex())
        token_file.write_text(token)
        key_file.chmod(0o600)
        token_file.chmod(0o600)
        arguments = [
            *("record", record, "--portal", live_server.url),
            *("--key-file", str(key_file), "--token-file", str(token_file)),
            *("--rpc", isolated_portal, "--contract", deployed.address),
        ]
        assert main(arguments) == 0, capsysbinary.readouterr().err.decode()
        captured = capsysbinary.readouterr()
        assert captured.out == _plaintext(1)  # the plaintext alone, on stdout
        err = captured.err.decode()
        for check in ("chain", "anchored envelope", "merkle path", "rootOf", "decryption"):
            assert f"ok   {check}: " in err, err
        for check in ("same record", "signature", "robotKeyOf"):
            assert f"ok   {check}: " in err, err
        assert f"OK record {record}: genuine" in err

    # Another contract than the one the proof names: nothing printed, the check named.
    key_file = tmp_path / "alice.sm4"
    other = "0x" + "11" * 20
    arguments[arguments.index("--contract") + 1] = other
    arguments[arguments.index("--key-file") + 1] = str(key_file)
    arguments[arguments.index("--token-file") + 1] = str(tmp_path / "alice.token")
    assert main(arguments) == 1
    captured = capsysbinary.readouterr()
    assert captured.out == b""
    assert b"FAIL chain: the proof names contract" in captured.err
    # A key file others may read, a record that is not there, a portal that is not there.
    key_file.chmod(0o644)
    assert main(arguments) == 2
    assert b"chmod 600" in capsysbinary.readouterr().err
    key_file.chmod(0o600)
    arguments[1] = str(uuid.uuid4())
    assert main(arguments) == 2
    assert b"the portal answered 404" in capsysbinary.readouterr().err
    arguments[arguments.index("--portal") + 1] = "http://127.0.0.1:9"
    assert main(arguments) == 2


def _resealed(content: dict, key: bytes, header: dict, plaintext: bytes) -> dict:
    return {**content, "envelope": base64.b64encode(envelope.seal(key, header, plaintext)).decode()}


def _opened(content: dict, key: bytes) -> tuple[dict, bytes]:
    return envelope.open(key, base64.b64decode(content["envelope"]))


def _flip(text: str, position: int) -> str:
    """A base64 text with one byte of what it encodes changed."""
    raw = bytearray(base64.b64decode(text))
    raw[position] ^= 0x01
    return base64.b64encode(bytes(raw)).decode()


def _other_hex(value: str) -> str:
    """The hex text with its last digit changed."""
    return value[:-1] + ("1" if value[-1] != "1" else "2")


def test_each_lie_of_the_portal_fails_naming_its_check(shared, deployed):
    chain = ChainReader(deployed.w3)
    first, second = shared["records"]
    for viewer, (key, token) in shared["viewers"].items():
        content, proof = _answers(token, first)
        good = record_check(record=first, content=content, proof=proof, key=key, chain=chain)
        assert good.genuine, [(o.check, o.detail) for o in good.outcomes]
        assert good.plaintext == _plaintext(1)
        header, plaintext = _opened(content, key)
        other_content, other_proof = _answers(token, second)
        lies = {
            # the content: another plaintext of the same length, sealed with the same header
            "other plaintext": (
                _resealed(content, key, header, plaintext.replace(b"reading 1", b"reading 9")),
                proof,
                # the owner's key opens the anchored envelope: the content is not its plaintext
                "same record" if viewer == "alice" else "signature",
            ),
            "other header": (
                _resealed(content, key, {**header, "seq": 7}, plaintext),
                proof,
                "same record",
            ),
            "other record's content": (other_content, proof, "same record"),
            "sealed under another key": (
                _resealed(content, sm4.generate_key(), header, plaintext),
                proof,
                "decryption",
            ),
            # the proof
            "changed envelope": (
                content,
                {**proof, "envelope": _flip(proof["envelope"], 60)},
                "anchored envelope",
            ),
            "other record's envelope": (
                content,
                {**proof, "envelope": other_proof["envelope"], "digest": other_proof["digest"]},
                "merkle path",
            ),
            "changed path": (
                content,
                {**proof, "path": [_other_hex(proof["path"][0])]},
                "merkle path",
            ),
            "other block": (
                content,
                {**proof, "anchor": {**proof["anchor"], "block": proof["anchor"]["block"] + 1}},
                "rootOf",
            ),
            "other transaction": (
                content,
                {**proof, "anchor": {**proof["anchor"], "tx": "0x" + "ab" * 32}},
                "rootOf",
            ),
            "no signature": (content, {**proof, "signature": None}, "signature"),
        }
        for name, changed in (
            ("signer", "0" * 64),
            ("sig", _other_hex(proof["signature"]["sig"])),
            ("public_key", sm2.generate_keypair()[1]),
        ):
            lies[f"other {name}"] = (
                content,
                {**proof, "signature": {**proof["signature"], name: changed}},
                "signature",
            )
        for lie, (lied_content, lied_proof, check) in lies.items():
            checked = record_check(
                record=first, content=lied_content, proof=lied_proof, key=key, chain=chain
            )
            assert check in _failed(checked), (viewer, lie, checked.outcomes)
            assert checked.plaintext is None, (viewer, lie)
            if lie == "other transaction":  # a node without it says so, not "not successful"
                details = [o.detail for o in checked.outcomes if o.check == "rootOf"]
                assert any("not known to this node" in detail for detail in details), details

        for contract, chain_id in ((deployed.address, 1), ("0x" + "11" * 20, None)):
            checked = record_check(
                record=first,
                content=content,
                proof=proof,
                key=key,
                chain=chain,
                contract=contract,
                chain_id=chain_id,
            )
            assert _failed(checked) == ["chain"], checked.outcomes


def test_a_record_forged_with_the_owners_key_and_eoa_fails_at_robot_key_of(shared, deployed):
    """What the portal's KEK gives (the owner's SM4 key and EOA) is not enough: a record
    sealed and anchored with them but signed by another key, or by the robot's key after it was
    revoked, fails at robotKeyOf."""
    alice = shared["alice"]
    key, _token = shared["viewers"]["alice"]
    plaintext = _plaintext(3)

    def lying_answers(data: bytes, public_key: str) -> tuple[dict, dict]:
        proof = forged_proof(alice, deployed, data)
        header = envelope.read_header(data).header
        proof["envelope"] = base64.b64encode(data).decode()
        proof["signature"] = {
            "signer": header["signer"],
            "public_key": public_key,
            "sig": header["sig"],
            "key_owner": alice.owner.eoa_address,
            "key_added_block": 1,
            "key_revoked_block": None,
        }
        content = {"id": proof["record"], "verified": True, "digest": proof["digest"]}
        return {**content, "envelope": proof["envelope"]}, proof

    def sealed(signing_key: tuple[str, str]) -> bytes:
        return seal_for(alice.robot, key, seq=3, plaintext=plaintext, signing_key=signing_key)

    other = sm2.generate_keypair()
    content, proof = lying_answers(sealed(other), other[1])
    checked = record_check(
        record=proof["record"],
        content=content,
        proof=proof,
        key=key,
        chain=ChainReader(deployed.w3),
    )
    assert _failed(checked) == ["robotKeyOf"], checked.outcomes
    assert "never registered on chain" in checked.failed[0].detail

    # The robot's own key, revoked (unpaired); a record signed with it afterwards.
    deployed.robot_key_revoke(
        owner_eoa_account(alice.owner), bytes.fromhex(provenance.key_hash(alice.signing_key[1]))
    )
    content, proof = lying_answers(sealed(alice.signing_key), alice.signing_key[1])
    checked = record_check(
        record=proof["record"],
        content=content,
        proof=proof,
        key=key,
        chain=ChainReader(deployed.w3),
    )
    assert _failed(checked) == ["robotKeyOf"], checked.outcomes
    assert "revoked in block" in checked.failed[0].detail


def test_an_unsigned_record_is_never_genuine(
    make_robot, make_owner_token, deployed, django_capture_on_commit_callbacks
):
    setup = make_robot("carol")  # added by hand: it signs nothing
    with django_capture_on_commit_callbacks(execute=True):
        (record,) = record_create_batch(
            robot=setup.robot, envelopes=[setup.seal(1, plaintext=_plaintext(1))]
        )
    content, proof = _answers(make_owner_token(setup.owner, scopes=("read",))[1], str(record.pk))
    assert proof["signature"] is None
    arguments = {
        "record": str(record.pk),
        "content": content,
        "proof": proof,
        "key": setup.key,
        "chain": ChainReader(deployed.w3),
    }
    checked = record_check(**arguments)
    assert _failed(checked) == ["signature"]
    assert checked.failed[0].detail.startswith("unsigned")
    assert checked.plaintext is None
    allowed = record_check(**arguments, allow_unsigned=True)
    assert (allowed.failed, allowed.genuine, allowed.signed) == ([], False, False)
    assert allowed.plaintext == _plaintext(1)
    # A signature the anchored envelope does not carry is refused.
    lied = copy.deepcopy(proof)
    lied["signature"] = {"signer": "0" * 64, "sig": "0" * 128, "public_key": "04" + "0" * 128}
    assert _failed(record_check(**{**arguments, "proof": lied})) == ["signature"]


def test_a_record_signed_in_a_batch_is_genuine_and_its_batch_place_checked(
    make_paired_robot, django_capture_on_commit_callbacks, make_owner_token, deployed, monkeypatch
):
    """Provenance v2: a batch of three records signed once; each record is checked alone, its
    leaf folded up its path to the root the batch's signature is over (read from its anchored
    envelope's header). A proof that states another place in the batch, or another
    topic_seq, fails the signature check."""
    alice = make_paired_robot("alice")
    records = []
    for number in range(3):
        header = {
            "owner": alice.owner.username,
            "robot": str(alice.robot.id),
            "topic": "/chatter",
            "type": "std_msgs/String",
            "seq": number + 1,
            "time": f"2026-05-01T12:00:0{number}.000001Z",
            "topic_seq": number,
        }
        records.append((header, _plaintext(number)))
    headers = provenance.sign_batch(*alice.signing_key, records)
    envelopes = [
        envelope.seal(alice.key, header, plaintext)
        for header, (_, plaintext) in zip(headers, records, strict=True)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        stored = record_create_batch(robot=alice.robot, envelopes=envelopes)
    token = make_owner_token(alice.owner, scopes=("read",))[1]
    chain = ChainReader(deployed.w3)
    record = str(stored[1].pk)
    content, proof = _answers(token, record)
    checked = record_check(record=record, content=content, proof=proof, key=alice.key, chain=chain)
    assert checked.genuine, [(o.check, o.detail) for o in checked.failed]
    assert checked.plaintext == _plaintext(1)
    (signature,) = [o for o in checked.outcomes if o.check == "signature"]
    root = "0x" + provenance.batch_root(headers[1], _plaintext(1)).hex()
    assert f"its upload batch of 3 records (root {root}), this record #1" in signature.detail
    assert "topic_seq 1 on /chatter" in signature.detail

    # The proof's batch and topic_seq (as the proof answer states them for a v2 record) are
    # checked against the header and the root the record folds to.
    place = {"sig_index": 1, "sig_size": 3, "sig_path": headers[1]["sig_path"], "root": root}
    stated = {**proof, "batch": place, "topic_seq": 1}
    checked = record_check(record=record, content=content, proof=stated, key=alice.key, chain=chain)
    assert checked.genuine, [(o.check, o.detail) for o in checked.failed]
    for lie in (
        {"batch": {**place, "sig_index": 0}},
        {"batch": {**place, "root": "0x" + "00" * 32}},
        {"batch": {**place, "sig_size": 4}},
        {"topic_seq": 2},
    ):
        checked = record_check(
            record=record, content=content, proof={**stated, **lie}, key=alice.key, chain=chain
        )
        assert _failed(checked) == ["signature"], lie

    # One SM2 verification for the record: its batch's.
    counted = []
    verify = sm2.verify
    monkeypatch.setattr(sm2, "verify", lambda *args: counted.append(1) or verify(*args))
    record_check(record=record, content=content, proof=proof, key=alice.key, chain=chain)
    assert len(counted) == 1
