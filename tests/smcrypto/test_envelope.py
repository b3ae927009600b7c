"""Envelope v1 (DESIGN.md "Wire formats"): layout, header rules, tamper and garbage resistance."""

import contextlib
import dataclasses
import json
import struct
from datetime import UTC
from typing import Any

import pytest
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes
from gmssl.sm3 import sm3_hash
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smcrypto import envelope
from smcrypto.errors import (
    AuthenticationFailed,
    CryptoError,
    InvalidKey,
    MalformedEnvelope,
    UnsupportedEnvelope,
    WrongKey,
)

KEY = bytes.fromhex("00112233445566778899aabbccddeeff")
OTHER_KEY = bytes.fromhex("ffeeddccbbaa99887766554433221100")
NONCE = bytes.fromhex("000102030405060708090a0b")
HEADER = {
    "owner": "alice",
    "robot": "7d6f0c1e-robot",
    "topic": "/odom",
    "type": "nav_msgs/Odometry",
    "seq": 42,
    "time": "2026-11-21T14:00:00.123456Z",
}
PLAINTEXT = b'{"K": {"x": 1.5}, "Owner": "alice"}'


def _gmssl_sm3(data: bytes) -> bytes:
    return bytes.fromhex(sm3_hash(list(data)))


def _frame(header_bytes: bytes, plaintext: bytes = b"payload", key: bytes = KEY) -> bytes:
    """Build a correctly encrypted envelope by hand around any header bytes."""
    prefix = b"AR\x01\x01" + _gmssl_sm3(key)[:8] + NONCE + struct.pack(">I", len(header_bytes))
    aad = prefix + header_bytes
    encryptor = Cipher(algorithms.SM4(key), modes.GCM(NONCE)).encryptor()
    encryptor.authenticate_additional_data(aad)
    return aad + encryptor.update(plaintext) + encryptor.finalize() + encryptor.tag


def _canonical(header: dict[str, Any]) -> bytes:
    return json.dumps(header, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode()


SEALED = envelope.seal(KEY, HEADER, PLAINTEXT, nonce=NONCE)

non_empty_text = st.text(min_size=1, max_size=30)
json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**63)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=8,
)
utc_times = st.datetimes(timezones=st.just(UTC)).map(
    lambda moment: moment.isoformat().replace("+00:00", "Z")
)


@st.composite
def headers(draw: st.DrawFn) -> dict[str, Any]:
    extra_names = st.text(max_size=10).filter(
        lambda name: name not in envelope.HEADER_FIELDS and name not in envelope.SIGNATURE_FIELDS
    )
    header = draw(st.dictionaries(extra_names, json_values, max_size=3))
    header.update(
        owner=draw(non_empty_text),
        robot=draw(non_empty_text),
        topic=draw(non_empty_text),
        type=draw(non_empty_text),
        seq=draw(st.integers(0, envelope.MAX_SEQ)),
        time=draw(utc_times),
    )
    return header


def test_layout_matches_design_byte_for_byte() -> None:
    assert _frame(_canonical(HEADER), PLAINTEXT) == SEALED
    assert SEALED[:4] == b"AR\x01\x01"
    assert SEALED[4:12] == _gmssl_sm3(KEY)[:8] == envelope.key_id(KEY)
    assert SEALED[12:24] == NONCE
    header_length = int.from_bytes(SEALED[24:28], "big")
    assert SEALED[28 : 28 + header_length] == (
        b'{"owner":"alice","robot":"7d6f0c1e-robot","seq":42,'
        b'"time":"2026-11-21T14:00:00.123456Z","topic":"/odom","type":"nav_msgs/Odometry"}'
    )
    assert len(SEALED) == 28 + header_length + len(PLAINTEXT) + 16


def test_constants() -> None:
    assert envelope.MAGIC == b"AR"
    assert envelope.VERSION == envelope.ALG_SM4_GCM == 1
    assert envelope.MAX_HEADER_LENGTH == 65536
    assert envelope.MAX_HEADER_DEPTH == 32
    assert envelope.MIN_ENVELOPE_SIZE == 44
    assert set(envelope.HEADER_FIELDS) == {"owner", "robot", "topic", "type", "seq", "time"}


def test_open_returns_header_and_plaintext() -> None:
    assert envelope.open(KEY, SEALED) == (HEADER, PLAINTEXT)


def test_read_header_without_key() -> None:
    info = envelope.read_header(SEALED)
    assert info == envelope.EnvelopeInfo(
        version=1,
        algorithm=1,
        key_id=envelope.key_id(KEY),
        nonce=NONCE,
        header=HEADER,
        header_bytes=_canonical(HEADER),
        ciphertext_length=len(PLAINTEXT),
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        info.version = 2


def test_random_nonce_differs_each_time() -> None:
    first, second = envelope.seal(KEY, HEADER, b"x"), envelope.seal(KEY, HEADER, b"x")
    assert first != second
    assert envelope.open(KEY, first) == envelope.open(KEY, second) == (HEADER, b"x")


def test_bytes_like_envelopes_accepted() -> None:
    assert envelope.open(KEY, bytearray(SEALED)) == (HEADER, PLAINTEXT)
    assert envelope.read_header(memoryview(SEALED)).header == HEADER


def test_non_ascii_header_is_utf8_not_escaped() -> None:
    header = {**HEADER, "owner": "机器人", "topic": "/caméra"}
    sealed = envelope.seal(KEY, header, b"")
    assert "机器人".encode() in sealed
    assert envelope.open(KEY, sealed) == (header, b"")


@settings(max_examples=150, deadline=None)
@given(header=headers(), plaintext=st.binary(max_size=3000))
def test_round_trip(header: dict[str, Any], plaintext: bytes) -> None:
    sealed = envelope.seal(KEY, header, plaintext)
    assert envelope.open(KEY, sealed) == (header, plaintext)
    info = envelope.read_header(sealed)
    assert info.header == header
    assert info.ciphertext_length == len(plaintext)


def test_every_single_byte_change_is_refused() -> None:
    for index in range(len(SEALED)):
        for flip in (0x01, 0x80, 0xFF):
            tampered = bytearray(SEALED)
            tampered[index] ^= flip
            with pytest.raises(CryptoError):
                envelope.open(KEY, bytes(tampered))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), header=headers(), plaintext=st.binary(max_size=200))
def test_any_byte_change_is_refused(data: st.DataObject, header: dict, plaintext: bytes) -> None:
    sealed = bytearray(envelope.seal(KEY, header, plaintext))
    index = data.draw(st.integers(0, len(sealed) - 1))
    sealed[index] ^= data.draw(st.integers(1, 255))
    with pytest.raises(CryptoError):
        envelope.open(KEY, bytes(sealed))


def test_every_truncation_is_refused() -> None:
    for length in range(len(SEALED)):
        with pytest.raises(CryptoError):
            envelope.open(KEY, SEALED[:length])


def test_truncation_error_types() -> None:
    with pytest.raises(MalformedEnvelope, match="magic"):
        envelope.read_header(b"")
    with pytest.raises(MalformedEnvelope, match="truncated"):
        envelope.read_header(SEALED[:43])
    with pytest.raises(MalformedEnvelope, match="truncated"):
        envelope.read_header(SEALED[: 28 + len(_canonical(HEADER)) + 15])
    with pytest.raises(AuthenticationFailed):
        envelope.open(KEY, SEALED[:-1])


def test_appended_bytes_fail_authentication() -> None:
    with pytest.raises(AuthenticationFailed):
        envelope.open(KEY, SEALED + b"\x00")


def test_wrong_key() -> None:
    with pytest.raises(WrongKey, match="key id"):
        envelope.open(OTHER_KEY, SEALED)


@pytest.mark.parametrize("offset_from_end", [1, 16, 17, len(PLAINTEXT) + 16])
def test_ciphertext_or_tag_change_fails_authentication(offset_from_end: int) -> None:
    tampered = bytearray(SEALED)
    tampered[-offset_from_end] ^= 0x01
    with pytest.raises(AuthenticationFailed):
        envelope.open(KEY, bytes(tampered))


def test_valid_but_changed_header_fails_authentication() -> None:
    tampered = SEALED.replace(b'"owner":"alice"', b'"owner":"alicf"')
    assert envelope.read_header(tampered).header["owner"] == "alicf"
    with pytest.raises(AuthenticationFailed):
        envelope.open(KEY, tampered)


def test_nonce_or_key_id_change() -> None:
    tampered = bytearray(SEALED)
    tampered[12] ^= 0x01
    with pytest.raises(AuthenticationFailed):
        envelope.open(KEY, bytes(tampered))
    tampered = bytearray(SEALED)
    tampered[4] ^= 0x01
    with pytest.raises(WrongKey):
        envelope.open(KEY, bytes(tampered))


def test_check_order_parse_then_key_id_then_tag() -> None:
    malformed = SEALED[:3] + b"\x09" + SEALED[4:]
    with pytest.raises(UnsupportedEnvelope):
        envelope.open(OTHER_KEY, malformed)
    tampered_tag = SEALED[:-1] + bytes([SEALED[-1] ^ 1])
    with pytest.raises(WrongKey):
        envelope.open(OTHER_KEY, tampered_tag)


def test_bad_magic_version_algorithm() -> None:
    with pytest.raises(MalformedEnvelope, match="magic"):
        envelope.read_header(b"RA" + SEALED[2:])
    with pytest.raises(UnsupportedEnvelope, match="version 2"):
        envelope.read_header(SEALED[:2] + b"\x02" + SEALED[3:])
    with pytest.raises(UnsupportedEnvelope, match="algorithm 2"):
        envelope.read_header(SEALED[:3] + b"\x02" + SEALED[4:])
    with pytest.raises(UnsupportedEnvelope):
        envelope.read_header(b"AR\x00")


@settings(max_examples=300, deadline=None)
@given(garbage=st.binary(max_size=300))
def test_garbage_raises_only_crypto_errors(garbage: bytes) -> None:
    for candidate in (garbage, b"AR\x01\x01" + garbage, SEALED[:28] + garbage):
        with pytest.raises(CryptoError):
            envelope.open(KEY, candidate)
        with contextlib.suppress(CryptoError):
            envelope.read_header(candidate)


@settings(max_examples=300, deadline=None)
@given(header_bytes=st.binary(max_size=200) | st.text(max_size=200).map(str.encode))
def test_arbitrary_header_bytes_raise_only_malformed(header_bytes: bytes) -> None:
    try:
        info = envelope.read_header(_frame(header_bytes))
    except MalformedEnvelope:
        return
    assert info.header_bytes == header_bytes


@pytest.mark.parametrize(
    "header_bytes",
    [
        json.dumps(HEADER, sort_keys=True).encode(),  # spaces
        json.dumps(HEADER, separators=(",", ":")).encode(),  # not sorted
        _canonical(HEADER) + b" ",
        b"\xef\xbb\xbf" + _canonical(HEADER),
        _canonical({**HEADER, "owner": "é"}).replace("é".encode(), b"\\u00e9"),
        _canonical({**HEADER, "x": 1}).replace(b'"x":1', b'"x":1e0'),
        _canonical(HEADER)[:-1] + b',"type":"nav_msgs/Odometry"}',  # duplicate field
    ],
    ids=["spaces", "unsorted", "trailing-space", "bom", "ascii-escape", "exponent", "duplicate"],
)
def test_non_canonical_header_refused(header_bytes: bytes) -> None:
    framed = _frame(header_bytes)
    with pytest.raises(MalformedEnvelope):
        envelope.read_header(framed)
    with pytest.raises(MalformedEnvelope):
        envelope.open(KEY, framed)
    with pytest.raises(MalformedEnvelope):  # a check run's key, made once, refuses it alike
        envelope.OpeningKey(KEY).open(framed)


def test_one_opening_key_opens_many_envelopes_as_open_does() -> None:
    """OpeningKey makes the key's id and cipher once for a run: each envelope opened as
    `open` opens it, a wrong key, a changed byte and a header read from other bytes refused
    as `open` refuses them."""
    opening = envelope.OpeningKey(KEY)
    sealed = [envelope.seal(KEY, {**HEADER, "seq": seq}, b"x" * seq) for seq in range(5)]
    for data in sealed:
        assert opening.open(data) == envelope.open(KEY, data)
        assert opening.open(data, info=envelope.read_header(data)) == envelope.open(KEY, data)
    other = envelope.seal(bytes(16), HEADER, PLAINTEXT)
    with pytest.raises(WrongKey):
        opening.open(other)
    changed = bytearray(sealed[1])
    changed[-1] ^= 1
    with pytest.raises(AuthenticationFailed):
        opening.open(bytes(changed))
    with pytest.raises(MalformedEnvelope):
        opening.open(sealed[1], info=envelope.read_header(sealed[2]))
    with pytest.raises(MalformedEnvelope):
        opening.open("not bytes")  # type: ignore[arg-type]
    with pytest.raises(InvalidKey):
        envelope.OpeningKey(b"short")


@pytest.mark.parametrize(
    "header_bytes",
    [
        b"",
        b"[]",
        b"1",
        b'"owner"',
        b"null",
        b"\xff\xfe",
        b'{"owner":"\xc3"}',
        b'{"owner":NaN}',
        b'{"owner":Infinity}',
        b'{"owner":"\\ud800"}',
        b"[" * 60000,
        b'{"a":' + b"[" * 30000 + b"]" * 30000 + b"}",
        b'{"seq":' + b"9" * 5000 + b"}",
    ],
)
def test_header_not_a_json_object_refused(header_bytes: bytes) -> None:
    with pytest.raises(MalformedEnvelope):
        envelope.read_header(_frame(header_bytes))


BAD_FIELDS = [
    ("owner", ""),
    ("owner", None),
    ("owner", 7),
    ("robot", ""),
    ("robot", ["r"]),
    ("topic", ""),
    ("type", {"ros": "x"}),
    ("seq", -1),
    ("seq", True),
    ("seq", 1.0),
    ("seq", "1"),
    ("seq", 2**63),
    ("time", "2026-11-21T14:00:00"),
    ("time", "2026-11-21T14:00:00+01:00"),
    ("time", "yesterday"),
    ("time", ""),
    ("time", 1763733600),
]


@pytest.mark.parametrize(("name", "value"), BAD_FIELDS)
def test_bad_header_field_refused_when_sealing_and_reading(name: str, value: Any) -> None:
    header = {**HEADER, name: value}
    with pytest.raises(MalformedEnvelope, match=name):
        envelope.seal(KEY, header, b"")
    with pytest.raises(MalformedEnvelope, match=name):
        envelope.read_header(_frame(_canonical(header)))


@pytest.mark.parametrize("name", envelope.HEADER_FIELDS)
def test_missing_header_field_refused(name: str) -> None:
    header = {field: value for field, value in HEADER.items() if field != name}
    with pytest.raises(MalformedEnvelope, match=f"missing field.*{name}"):
        envelope.seal(KEY, header, b"")
    with pytest.raises(MalformedEnvelope, match=name):
        envelope.read_header(_frame(_canonical(header)))


@pytest.mark.parametrize(
    "time", ["2026-11-21T14:00:00Z", "2026-11-21T14:00:00+00:00", "2026-11-21T14:00:00.1Z"]
)
def test_utc_time_forms_accepted(time: str) -> None:
    header = {**HEADER, "time": time}
    assert envelope.open(KEY, envelope.seal(KEY, header, b"")) == (header, b"")


@pytest.mark.parametrize(
    "header",
    [
        {**HEADER, "extra": (1, 2)},
        {**HEADER, "extra": {1: "x"}},
        {**HEADER, "extra": float("nan")},
        {**HEADER, "extra": float("inf")},
        {**HEADER, "extra": b"bytes"},
        {**HEADER, "extra": "\ud800"},
        {**HEADER, 1: "x"},
        [("owner", "alice")],
        None,
    ],
    ids=["tuple", "int-key", "nan", "inf", "bytes", "surrogate", "top-int-key", "list", "none"],
)
def test_header_that_is_not_plain_json_refused(header: Any) -> None:
    with pytest.raises(MalformedEnvelope):
        envelope.seal(KEY, header, b"")


def test_nesting_depth_limit() -> None:
    def nested(levels: int) -> dict[str, Any]:
        value: Any = []
        for _ in range(levels - 2):
            value = [value]
        return {**HEADER, "deep": value}

    at_limit = nested(envelope.MAX_HEADER_DEPTH)
    assert envelope.open(KEY, envelope.seal(KEY, at_limit, b"")) == (at_limit, b"")
    too_deep = nested(envelope.MAX_HEADER_DEPTH + 1)
    with pytest.raises(MalformedEnvelope, match="nested deeper than 32"):
        envelope.seal(KEY, too_deep, b"")
    with pytest.raises(MalformedEnvelope, match="nested deeper than 32"):
        envelope.read_header(_frame(_canonical(too_deep)))
    brackets_in_strings = {**HEADER, "note": "[{" * 1000 + '\\"[' * 100}
    assert envelope.open(KEY, envelope.seal(KEY, brackets_in_strings, b""))[0] == (
        brackets_in_strings
    )


def test_circular_header_refused() -> None:
    header: dict[str, Any] = dict(HEADER)
    header["self"] = header
    with pytest.raises(MalformedEnvelope):
        envelope.seal(KEY, header, b"")


def test_extra_json_fields_round_trip() -> None:
    header = {**HEADER, "frame_id": "base_link", "size": [640, 480], "meta": {"k": None}}
    assert envelope.open(KEY, envelope.seal(KEY, header, b"")) == (header, b"")


def test_header_length_limit() -> None:
    filler = envelope.MAX_HEADER_LENGTH - len(_canonical({**HEADER, "pad": ""}))
    at_limit = {**HEADER, "pad": "x" * filler}
    assert len(_canonical(at_limit)) == envelope.MAX_HEADER_LENGTH
    assert envelope.open(KEY, envelope.seal(KEY, at_limit, b"")) == (at_limit, b"")
    with pytest.raises(MalformedEnvelope, match="over the limit"):
        envelope.seal(KEY, {**HEADER, "pad": "x" * (filler + 1)}, b"")
    oversized = _frame(_canonical({**HEADER, "pad": "x" * (filler + 1)}))
    with pytest.raises(MalformedEnvelope, match="exceeds the limit"):
        envelope.read_header(oversized)
    claims_4gb = SEALED[:24] + b"\xff\xff\xff\xff" + SEALED[28:]
    with pytest.raises(MalformedEnvelope, match="exceeds the limit"):
        envelope.read_header(claims_4gb)


@pytest.mark.parametrize("key", [b"", bytes(15), bytes(17), "k" * 16, None])
def test_bad_key(key: Any) -> None:
    with pytest.raises(InvalidKey, match="SM4 key"):
        envelope.seal(key, HEADER, b"")
    with pytest.raises(InvalidKey, match="SM4 key"):
        envelope.open(key, SEALED)
    with pytest.raises(InvalidKey, match="SM4 key"):
        envelope.key_id(key)


@pytest.mark.parametrize("nonce", [b"", bytes(11), bytes(13), "n" * 12])
def test_bad_nonce(nonce: Any) -> None:
    with pytest.raises(InvalidKey, match="nonce"):
        envelope.seal(KEY, HEADER, b"", nonce=nonce)


@pytest.mark.parametrize("value", ["AR", None, 7, [65, 82]])
def test_non_bytes_envelope(value: Any) -> None:
    with pytest.raises(MalformedEnvelope, match="must be bytes"):
        envelope.read_header(value)


def test_digest_is_sm3_of_the_envelope() -> None:
    assert envelope.digest(SEALED) == _gmssl_sm3(SEALED)
    assert len(envelope.digest(b"")) == 32


def test_key_id() -> None:
    assert envelope.key_id(KEY) == _gmssl_sm3(KEY)[:8]
    assert envelope.key_id(KEY) != envelope.key_id(OTHER_KEY)


def test_key_commitment_known_answer() -> None:
    address = "0x52908400098527886E0F7030069857D2E4169EE7"
    expected = _gmssl_sm3(b"AuthROS/key-commitment/v1" + bytes.fromhex(address[2:]) + KEY)
    assert envelope.key_commitment(address, KEY) == expected
    assert expected.hex() == "ad69e648695bfe625b2667b7a90fd07987d786542375b48cf153a769f23742bf"
    assert envelope.key_commitment(address.lower(), KEY) == expected
    assert envelope.key_commitment("0X" + address[2:], KEY) == expected
    assert envelope.key_commitment(bytes.fromhex(address[2:]), KEY) == expected
    assert envelope.key_commitment(address, OTHER_KEY) != expected


@pytest.mark.parametrize(
    "address",
    [
        "",
        "0x",
        "52908400098527886E0F7030069857D2E4169EE7",
        "0x52908400098527886E0F7030069857D2E4169EE",
        "0x52908400098527886E0F7030069857D2E4169EE7aa",
        "0x52908400098527886E0F7030069857D2E4169EEg",
        "0x52908400098527886E0F7030069857D2E4169EE7\n",
        bytes(19),
        bytes(21),
        None,
    ],
)
def test_key_commitment_bad_address(address: Any) -> None:
    with pytest.raises(InvalidKey, match="EOA address"):
        envelope.key_commitment(address, KEY)


def test_key_commitment_bad_key() -> None:
    with pytest.raises(InvalidKey, match="SM4 key"):
        envelope.key_commitment("0x" + "00" * 20, bytes(15))


def test_open_with_the_header_read_already_is_open() -> None:
    """An upload reads each header first, then opens with it (`info`): the same answer, and
    a header read from other bytes is refused rather than trusted."""
    info = envelope.read_header(SEALED)
    assert envelope.open(KEY, SEALED, info=info) == envelope.open(KEY, SEALED)
    other = envelope.seal(KEY, {**HEADER, "seq": 43}, PLAINTEXT)
    with pytest.raises(MalformedEnvelope, match="not this envelope's"):
        envelope.open(KEY, other, info=info)
    with pytest.raises(MalformedEnvelope, match="not this envelope's"):
        envelope.open(KEY, SEALED[:40], info=info)
    renonced = envelope.seal(KEY, HEADER, PLAINTEXT)  # a fresh nonce, the same header
    with pytest.raises(MalformedEnvelope, match="not this envelope's"):
        envelope.open(KEY, renonced, info=info)


def test_every_single_byte_change_is_refused_with_the_header_read_first() -> None:
    for index in range(len(SEALED)):
        tampered = bytearray(SEALED)
        tampered[index] ^= 0x01
        with pytest.raises(CryptoError):
            envelope.open(KEY, bytes(tampered), info=envelope.read_header(bytes(tampered)))
