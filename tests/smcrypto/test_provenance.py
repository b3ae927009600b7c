"""Record signatures (DESIGN.md "Provenance"): pinned message bytes and signature, the checks
and their reasons, every byte of signer, sig, header and plaintext changed in turn caught, and
the envelope carrying, authenticating and exposing `signer` and `sig`."""

from typing import Any

import pytest
from gmssl.sm2 import CryptSM2
from gmssl.sm3 import sm3_hash

from smcrypto import envelope, provenance, sm2
from smcrypto.errors import (
    AuthenticationFailed,
    BadSignature,
    InvalidData,
    InvalidKey,
    MalformedEnvelope,
    SignatureInvalid,
    SignatureMalformed,
    SignatureMissing,
    SignerMismatch,
)

# GB/T 32918.5's example key pair and nonce (as in test_sm2)
PRIVATE = "3945208f7b2144b13f36e38ac6d39f95889393692860b51a42fb81ef4df7c5b8"
PUBLIC = (
    "04"
    "09f9df311e5421a150dd7d161e4bc5c672179fad1833fc076bb08ff356f35020"
    "ccea490ce26775a52dc6ea718cc1aa600aed05fbf35e084a6632f6072da9ad13"
)
NONCE_K = "59276e27d506861a16680f3ad9c02dccef3cc1fa3cdbe4ce6d54b80deac1bc21"
SIGNER = "3d92bed6d685f38bff5ccd052119e1ecc071c2f3d915245c8d9c5a2cb131a89d"
KEY = bytes.fromhex("00112233445566778899aabbccddeeff")
HEADER = {
    "owner": "alice",
    "robot": "7d6f0c1e-robot",
    "topic": "/odom",
    "type": "nav_msgs/Odometry",
    "seq": 42,
    "time": "2026-11-21T14:00:00.123456Z",
}
PLAINTEXT = b'{"K": {"x": 1.5}, "Owner": "alice"}'
PLAINTEXT_SM3 = "00cb09fb351ff85780808f7530b7ab669eec8e2faa6098eaf2c0b6864ee15bb6"
MESSAGE = (
    b"AuthROS/record-signature/v1\x00"
    b'{"owner":"alice","robot":"7d6f0c1e-robot","seq":42,'
    b'"signer":"3d92bed6d685f38bff5ccd052119e1ecc071c2f3d915245c8d9c5a2cb131a89d",'
    b'"time":"2026-11-21T14:00:00.123456Z","topic":"/odom","type":"nav_msgs/Odometry"}'
) + bytes.fromhex(PLAINTEXT_SM3)
# gmssl's sign_with_sm3 of MESSAGE with PRIVATE and the nonce NONCE_K
SIG = (
    "6227f201159cac8ce04681775e1f7ead792599e7c915a9a119b9e446475b2b93"
    "0080c1b38ddefbffd77b8c94021c82dedb51182961799feaeffebed4702205f7"
)
SIGNED = {**HEADER, "signer": SIGNER, "sig": SIG}


def _gmssl(private_key: str, public_key: str) -> CryptSM2:
    crypt = CryptSM2(private_key=private_key, public_key="", mode=1)
    crypt.public_key = public_key[-128:]  # past gmssl's lstrip("04")
    return crypt


def _other_hex_digit(digit: str) -> str:
    return "0123456789abcdef"[("0123456789abcdef".index(digit) + 1) % 16]


def _reason(public_key: str, header: Any, plaintext: bytes) -> str:
    try:
        provenance.signature_check(public_key, header, plaintext)
    except SignatureInvalid as exc:
        assert provenance.verify_header(public_key, header, plaintext) is False
        return exc.reason
    assert provenance.verify_header(public_key, header, plaintext) is True
    return "ok"


# --- pinned vectors ---------------------------------------------------------------------------


def test_the_key_hash_is_sm3_of_x_and_y():
    assert provenance.key_hash(PUBLIC) == SIGNER
    assert provenance.key_hash(PUBLIC[2:]) == SIGNER
    assert provenance.key_hash(PUBLIC.upper()[2:]) == SIGNER
    assert sm3_hash(list(bytes.fromhex(PUBLIC[2:]))) == SIGNER


@pytest.mark.parametrize("public_key", ["", PUBLIC[:-2], "04" + "11" * 64, "zz" * 65, None])
def test_the_key_hash_of_a_key_that_is_not_an_sm2_point_is_refused(public_key):
    with pytest.raises(InvalidKey):
        provenance.key_hash(public_key)


def test_the_message_bytes_of_a_fixed_header_are_pinned():
    assert provenance.signature_message({**HEADER, "signer": SIGNER}, PLAINTEXT) == MESSAGE
    # `sig` is left out, `signer` is in
    assert provenance.signature_message(SIGNED, PLAINTEXT) == MESSAGE
    assert provenance.signature_message({**SIGNED, "sig": "00" * 64}, PLAINTEXT) == MESSAGE
    assert provenance.signature_message(HEADER, PLAINTEXT) != MESSAGE
    assert sm3_hash(list(PLAINTEXT)) == PLAINTEXT_SM3


def test_the_header_in_the_message_is_the_envelopes_own_header_bytes():
    sealed = envelope.seal(KEY, HEADER, PLAINTEXT)
    header_bytes = envelope.read_header(sealed).header_bytes
    assert provenance.signature_message(HEADER, PLAINTEXT) == (
        provenance.SIGNATURE_DOMAIN + b"\x00" + header_bytes + bytes.fromhex(PLAINTEXT_SM3)
    )


def test_non_ascii_header_text_is_utf8_in_the_message():
    header = {**HEADER, "owner": "机器人", "topic": "/caméra"}
    message = provenance.signature_message(header, b"")
    assert '"owner":"机器人"'.encode() in message
    assert b"\\u" not in message


def test_the_pinned_signature_verifies_and_the_reference_reproduces_it():
    assert provenance.verify_header(PUBLIC, SIGNED, PLAINTEXT)
    assert _gmssl(PRIVATE, PUBLIC).sign_with_sm3(MESSAGE, NONCE_K) == SIG
    assert _gmssl(PRIVATE, PUBLIC).verify_with_sm3(SIG, MESSAGE)


# --- signing ----------------------------------------------------------------------------------


def test_a_signed_header_verifies_here_and_with_the_reference():
    private, public = sm2.generate_keypair()
    signed = provenance.sign_header(private, public, HEADER, PLAINTEXT)
    assert signed == {**HEADER, "signer": provenance.key_hash(public), "sig": signed["sig"]}
    assert envelope.is_lower_hex(signed["sig"], 128)
    assert provenance.verify_header(public, signed, PLAINTEXT)
    message = provenance.signature_message(signed, PLAINTEXT)
    assert _gmssl(private, public).verify_with_sm3(signed["sig"], message)


def test_signing_again_replaces_the_signature_and_leaves_the_header_given_alone():
    private, public = sm2.generate_keypair()
    given = dict(SIGNED)
    signed = provenance.sign_header(private, public, given, PLAINTEXT)
    assert given == SIGNED
    assert signed["signer"] == provenance.key_hash(public) != SIGNER
    assert provenance.verify_header(public, signed, PLAINTEXT)
    assert not provenance.verify_header(PUBLIC, signed, PLAINTEXT)


def test_signing_with_a_public_key_that_is_not_the_private_keys_is_refused():
    _, other_public = sm2.generate_keypair()
    with pytest.raises(InvalidKey, match="not the private key's"):
        provenance.sign_header(PRIVATE, other_public, HEADER, PLAINTEXT)


def test_a_plaintext_that_is_not_bytes_is_refused():
    with pytest.raises(InvalidData):
        provenance.sign_header(PRIVATE, PUBLIC, HEADER, "text")
    with pytest.raises(InvalidData):
        provenance.verify_header(PUBLIC, SIGNED, 5)
    assert provenance.verify_header(PUBLIC, SIGNED, bytearray(PLAINTEXT))


# --- every change caught, with its reason -----------------------------------------------------


def test_every_hex_digit_of_the_signer_changed_is_caught():
    for index in range(64):
        signer = SIGNER[:index] + _other_hex_digit(SIGNER[index]) + SIGNER[index + 1 :]
        assert _reason(PUBLIC, {**SIGNED, "signer": signer}, PLAINTEXT) == "signer_mismatch"


def test_every_hex_digit_of_the_sig_changed_is_caught():
    for index in range(128):
        sig = SIG[:index] + _other_hex_digit(SIG[index]) + SIG[index + 1 :]
        assert _reason(PUBLIC, {**SIGNED, "sig": sig}, PLAINTEXT) == "bad_signature"


def test_every_byte_of_the_plaintext_changed_is_caught():
    for index in range(len(PLAINTEXT)):
        for flip in (0x01, 0x80):
            changed = bytearray(PLAINTEXT)
            changed[index] ^= flip
            assert _reason(PUBLIC, SIGNED, bytes(changed)) == "bad_signature"
    assert _reason(PUBLIC, SIGNED, PLAINTEXT + b" ") == "bad_signature"
    assert _reason(PUBLIC, SIGNED, PLAINTEXT[:-1]) == "bad_signature"
    assert _reason(PUBLIC, SIGNED, b"") == "bad_signature"


def test_every_character_of_every_header_field_changed_is_caught():
    for name, value in HEADER.items():
        if isinstance(value, str):
            variants: list[Any] = [
                value[:index] + ("x" if value[index] != "x" else "y") + value[index + 1 :]
                for index in range(len(value))
            ]
        else:
            variants = [value + 1, value - 1, 0, value * 10, str(value)]
        for changed in variants:
            header = {**SIGNED, name: changed}
            assert _reason(PUBLIC, header, PLAINTEXT) == "bad_signature", (name, changed)


def test_a_field_added_or_removed_is_caught():
    assert _reason(PUBLIC, {**SIGNED, "frame_id": "base_link"}, PLAINTEXT) == "bad_signature"
    for name in HEADER:
        header = {field: value for field, value in SIGNED.items() if field != name}
        assert _reason(PUBLIC, header, PLAINTEXT) == "bad_signature", name


def test_another_robots_key_is_caught_whatever_signer_it_names():
    _, other_public = sm2.generate_keypair()
    assert _reason(other_public, SIGNED, PLAINTEXT) == "signer_mismatch"
    claims_other = {**SIGNED, "signer": provenance.key_hash(other_public)}
    assert _reason(other_public, claims_other, PLAINTEXT) == "bad_signature"


def test_every_hex_digit_of_the_public_key_changed_is_caught():
    for index in range(2, 130):
        public = PUBLIC[:index] + _other_hex_digit(PUBLIC[index]) + PUBLIC[index + 1 :]
        assert _reason(public, SIGNED, PLAINTEXT) in ("malformed", "signer_mismatch")


@pytest.mark.parametrize("missing", [("sig",), ("signer",), ("signer", "sig")])
def test_an_unsigned_header_is_missing_its_signature(missing):
    header = {name: value for name, value in SIGNED.items() if name not in missing}
    assert _reason(PUBLIC, header, PLAINTEXT) == "missing"
    with pytest.raises(SignatureMissing, match="unsigned"):
        provenance.signature_check(PUBLIC, header, PLAINTEXT)


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("signer", SIGNER.upper()),
        ("signer", SIGNER[:-1]),
        ("signer", SIGNER + "0"),
        ("signer", "g" + SIGNER[1:]),
        ("signer", int(SIGNER, 16)),
        ("signer", None),
        ("sig", SIG.upper()),
        ("sig", SIG[:-2]),
        ("sig", " " + SIG[1:]),
        ("sig", [SIG]),
    ],
)
def test_signer_and_sig_that_are_not_lowercase_hex_of_their_length_are_malformed(name, value):
    with pytest.raises(SignatureMalformed, match=name):
        provenance.signature_check(PUBLIC, {**SIGNED, name: value}, PLAINTEXT)


@pytest.mark.parametrize("public_key", ["", "04" + "11" * 64, PUBLIC[:-2], 7])
def test_a_public_key_that_is_not_an_sm2_point_is_malformed(public_key):
    assert _reason(public_key, SIGNED, PLAINTEXT) == "malformed"


@pytest.mark.parametrize("header", [None, [("owner", "alice")], {**SIGNED, "x": float("nan")}])
def test_a_header_that_is_not_plain_json_is_malformed(header):
    assert _reason(PUBLIC, header, PLAINTEXT) == "malformed"


def test_the_reasons_are_distinct_errors_of_one_family():
    kinds = (SignatureMissing, SignatureMalformed, SignerMismatch, BadSignature)
    assert {kind.reason for kind in kinds} == {
        "missing",
        "malformed",
        "signer_mismatch",
        "bad_signature",
    }
    assert all(issubclass(kind, SignatureInvalid) for kind in kinds)


# --- in the envelope --------------------------------------------------------------------------


def test_the_envelope_carries_and_exposes_the_signature():
    sealed = envelope.seal(KEY, SIGNED, PLAINTEXT)
    info = envelope.read_header(sealed)
    assert (info.signer, info.sig) == (SIGNER, SIG)
    header, plaintext = envelope.open(KEY, sealed)
    assert header == SIGNED
    assert provenance.verify_header(PUBLIC, header, plaintext)
    unsigned = envelope.read_header(envelope.seal(KEY, HEADER, PLAINTEXT))
    assert (unsigned.signer, unsigned.sig) == (None, None)


def test_every_byte_of_signer_and_sig_changed_in_a_sealed_envelope_is_refused():
    sealed = envelope.seal(KEY, SIGNED, PLAINTEXT)
    for value in (SIGNER, SIG):
        start = sealed.index(value.encode())
        for index in range(start, start + len(value)):
            changed = bytearray(sealed)
            changed[index] = ord(_other_hex_digit(chr(changed[index])))
            with pytest.raises(AuthenticationFailed):
                envelope.open(KEY, bytes(changed))
            changed[index] = ord(chr(sealed[index]).upper()) if chr(sealed[index]).isalpha() else 0
            with pytest.raises(MalformedEnvelope):
                envelope.open(KEY, bytes(changed))


@pytest.mark.parametrize(
    "fields",
    [
        {"signer": SIGNER},
        {"sig": SIG},
        {"signer": SIGNER.upper(), "sig": SIG},
        {"signer": SIGNER, "sig": SIG.upper()},
        {"signer": SIGNER[:-2], "sig": SIG},
        {"signer": SIGNER, "sig": SIG + "00"},
        {"signer": "", "sig": ""},
        {"signer": None, "sig": SIG},
        {"signer": SIGNER, "sig": 5},
        {"signer": "x" * 64, "sig": SIG},
    ],
)
def test_the_envelope_refuses_malformed_signature_fields_when_sealing_and_reading(fields):
    header = {**HEADER, **fields}
    with pytest.raises(MalformedEnvelope, match=r"signer|sig"):
        envelope.seal(KEY, header, PLAINTEXT)
    header_bytes = envelope.canonical_json(header)
    framed = envelope.seal(KEY, HEADER, PLAINTEXT)  # then its header replaced by hand
    prefix_size = envelope.PREFIX_SIZE
    old_length = int.from_bytes(framed[prefix_size - 4 : prefix_size], "big")
    forged = (
        framed[: prefix_size - 4]
        + len(header_bytes).to_bytes(4, "big")
        + header_bytes
        + framed[prefix_size + old_length :]
    )
    with pytest.raises(MalformedEnvelope, match=r"signer|sig"):
        envelope.read_header(forged)
