"""Batch signatures (DESIGN.md "Provenance v2"): leaves and the signed message computed
independently (gmssl's SM3 and SM2, not ours), one SM2 verification per batch, and every way a
record can be moved, changed or relabelled caught: another index, size or path, another
plaintext or header field, a v2 header read as v1."""

import json
from collections import Counter
from typing import Any

import pytest
from gmssl.sm2 import CryptSM2
from gmssl.sm3 import sm3_hash

from smcrypto import envelope, provenance, sm2
from smcrypto.errors import InvalidData, MalformedEnvelope, SignatureInvalid, SignatureMalformed

PRIVATE = "3945208f7b2144b13f36e38ac6d39f95889393692860b51a42fb81ef4df7c5b8"
PUBLIC = sm2.public_key_from_private(PRIVATE)
KEY = bytes.fromhex("00112233445566778899aabbccddeeff")


def _header(index: int, topic: str = "/odom") -> dict[str, Any]:
    return {
        "owner": "alice",
        "robot": "7d6f0c1e-robot",
        "topic": topic,
        "type": "nav_msgs/Odometry",
        "seq": 100 + index,
        "time": f"2026-11-21T14:00:{index:02d}.000000Z",
        "topic_seq": index,
    }


def _batch(n: int) -> list[tuple[dict[str, Any], bytes]]:
    return [(_header(i), f'{{"x": {i}}}'.encode()) for i in range(n)]


def _sm3(data: bytes) -> bytes:
    return bytes.fromhex(sm3_hash(list(data)))


def _reference_root(leaves: list[bytes]) -> bytes:
    """RFC 9162 2.1.1's MTH, written out here with gmssl's SM3."""
    if len(leaves) == 1:
        return leaves[0]
    k = 1 << ((len(leaves) - 1).bit_length() - 1)
    return _sm3(b"\x01" + _reference_root(leaves[:k]) + _reference_root(leaves[k:]))


def _reference_leaf(header: dict[str, Any], plaintext: bytes) -> bytes:
    kept = {
        k: v for k, v in header.items() if k not in {"sig", "sig_index", "sig_size", "sig_path"}
    }
    text = json.dumps(kept, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()
    return _sm3(b"\x00AuthROS/record-signature/v2\x00" + text + _sm3(plaintext))


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 13])
def test_a_signed_batch_matches_an_independent_reference(n: int) -> None:
    records = _batch(n)
    headers = provenance.sign_batch(PRIVATE, PUBLIC, records)
    leaves = [_reference_leaf(h, p) for h, (_, p) in zip(headers, records, strict=True)]
    root = _reference_root(leaves)
    message = b"AuthROS/batch-signature/v2\x00" + n.to_bytes(8, "big") + root
    reference = CryptSM2(private_key=PRIVATE, public_key=PUBLIC[2:], mode=1)
    assert {h["sig"] for h in headers} == {headers[0]["sig"]}
    assert reference.verify_with_sm3(headers[0]["sig"], message)
    for index, (header, (_, plaintext)) in enumerate(zip(headers, records, strict=True)):
        assert (header["sig_index"], header["sig_size"]) == (index, n)
        assert header["signer"] == provenance.key_hash(PUBLIC)
        assert provenance.batch_root(header, plaintext) == root
        provenance.signature_check(PUBLIC, header, plaintext)


def test_a_batch_costs_one_verification(monkeypatch: pytest.MonkeyPatch) -> None:
    records = _batch(50)
    headers = provenance.sign_batch(PRIVATE, PUBLIC, records)
    seen: Counter[int] = Counter()
    real = sm2.verify_many

    def counting(claims):
        seen["claims"] += len(claims)
        return real(claims)

    monkeypatch.setattr(sm2, "verify_many", counting)
    claims = [
        provenance.signature_claim(PUBLIC, h, p) for h, (_, p) in zip(headers, records, strict=True)
    ]
    assert provenance.claims_hold(claims) == [True] * 50
    assert seen["claims"] == 1


def _last_digit_changed(hex_text: str) -> str:
    """The hex text with its last digit changed (never left as it was: signatures are random)."""
    return hex_text[:-1] + ("1" if hex_text[-1] == "0" else "0")


def _fails(header: dict[str, Any], plaintext: bytes) -> bool:
    try:
        return not provenance.signature_claim(PUBLIC, header, plaintext).holds()
    except SignatureInvalid:
        return True


def test_every_change_to_a_record_of_a_batch_is_caught() -> None:
    records = _batch(5)
    headers = provenance.sign_batch(PRIVATE, PUBLIC, records)
    header, plaintext = headers[2], records[2][1]
    other = headers[3]
    changes = {
        "plaintext": (header, plaintext + b" "),
        "another index": ({**header, "sig_index": 3}, plaintext),
        "another size": ({**header, "sig_size": 6}, plaintext),
        "a smaller size": ({**header, "sig_size": 4}, plaintext),
        "another path": ({**header, "sig_path": other["sig_path"]}, plaintext),
        "a shorter path": ({**header, "sig_path": header["sig_path"][64:]}, plaintext),
        "topic_seq": ({**header, "topic_seq": 7}, plaintext),
        "time": ({**header, "time": "2026-11-21T14:00:59.000000Z"}, plaintext),
        "seq": ({**header, "seq": 1}, plaintext),
        "signature": ({**header, "sig": _last_digit_changed(header["sig"])}, plaintext),
        "swapped with its neighbour": (
            {**other, "sig_index": 2, "sig_path": header["sig_path"]},
            records[3][1],
        ),
    }
    assert not _fails(header, plaintext)
    caught = [name for name, (h, p) in changes.items() if _fails(h, p)]
    assert caught == list(changes)


def test_a_v2_record_cannot_pass_as_v1_or_unsigned() -> None:
    records = _batch(3)
    header = provenance.sign_batch(PRIVATE, PUBLIC, records)[1]
    plaintext = records[1][1]
    as_v1 = {k: v for k, v in header.items() if k not in {"sig_index", "sig_size", "sig_path"}}
    assert _fails(as_v1, plaintext)
    assert envelope.provenance_format(header) == "v2"
    assert envelope.provenance_format(as_v1) == "v1"
    sealed = envelope.seal(KEY, header, plaintext)
    info = envelope.read_header(sealed)
    assert info.provenance == "v2"
    assert envelope.open(KEY, sealed) == (header, plaintext)


@pytest.mark.parametrize(
    "change",
    [
        {"sig_size": 0},
        {"sig_size": "3"},
        {"sig_size": True},
        {"sig_index": 3},
        {"sig_index": -1},
        {"sig_path": "ABC"},
        {"sig_path": "0" * 63},
        {"topic_seq": -1},
        {"topic_seq": 1.5},
    ],
)
def test_an_envelope_refuses_batch_fields_of_the_wrong_shape(change: dict[str, Any]) -> None:
    records = _batch(3)
    header = {**provenance.sign_batch(PRIVATE, PUBLIC, records)[0], **change}
    with pytest.raises(MalformedEnvelope):
        envelope.seal(KEY, header, records[0][1])


@pytest.mark.parametrize("missing", ["sig", "signer", "sig_index", "sig_path", "topic_seq"])
def test_an_envelope_refuses_a_batch_header_missing_a_field(missing: str) -> None:
    records = _batch(2)
    header = dict(provenance.sign_batch(PRIVATE, PUBLIC, records)[0])
    del header[missing]
    with pytest.raises(MalformedEnvelope):
        envelope.seal(KEY, header, records[0][1])


def test_a_batch_needs_topic_seq_and_one_record() -> None:
    with pytest.raises(InvalidData):
        provenance.sign_batch(PRIVATE, PUBLIC, [])
    header = {k: v for k, v in _header(0).items() if k != "topic_seq"}
    with pytest.raises(InvalidData):
        provenance.sign_batch(PRIVATE, PUBLIC, [(header, b"x")])


def test_batch_root_refuses_a_path_that_cannot_fold() -> None:
    records = _batch(4)
    header = provenance.sign_batch(PRIVATE, PUBLIC, records)[0]
    with pytest.raises(SignatureMalformed):
        provenance.batch_root({**header, "sig_path": header["sig_path"] + "00" * 32}, records[0][1])
