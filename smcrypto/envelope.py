"""Envelope v1: the SM4-GCM sealed unit that is stored, hashed and anchored (DESIGN.md, fixed).

Layout, integers big-endian: magic `AR` | version 0x01 | algorithm 0x01 (SM4-GCM) |
key id (8) | nonce (12) | header length H (4) | header (H, canonical UTF-8 JSON) |
ciphertext || tag (16). The AAD is every byte before the ciphertext.

A robot's signature travels in the header (DESIGN.md "Provenance"): `signer` (64 lowercase
hex) and `sig` (128 lowercase hex), both or neither, authenticated like every header field.
A record signed as one of a batch (provenance v2) also carries `sig_index`, `sig_size`,
`sig_path` and `topic_seq` (DESIGN.md "Provenance v2"). Their shape is checked here; the
signature itself by smcrypto.provenance.
"""

import hmac
import json
import re
import secrets
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, NoReturn

from smcrypto import sm4
from smcrypto.errors import InvalidKey, MalformedEnvelope, UnsupportedEnvelope, WrongKey
from smcrypto.sm3 import sm3_digest

MAGIC = b"AR"
VERSION = 0x01
ALG_SM4_GCM = 0x01
KEY_ID_SIZE = 8
NONCE_SIZE = sm4.GCM_NONCE_SIZE
TAG_SIZE = sm4.GCM_TAG_SIZE
_PREFIX = struct.Struct(">2sBB8s12sI")  # magic, version, algorithm, key id, nonce, H
PREFIX_SIZE = _PREFIX.size
MIN_ENVELOPE_SIZE = PREFIX_SIZE + TAG_SIZE
MAX_HEADER_LENGTH = 64 * 1024
MAX_HEADER_DEPTH = 32
HEADER_FIELDS = ("owner", "robot", "seq", "time", "topic", "type")
# the robot's signature: field name -> its length in lowercase hex digits
SIGNATURE_FIELDS = {"signer": 64, "sig": 128}
# a batch signature's place (provenance v2): a header with `sig_size` is v2
BATCH_FIELDS = ("sig_index", "sig_size", "sig_path")
MAX_BATCH_SIZE = 2**20  # records under one batch signature
MAX_BATCH_PATH = 21  # hashes in the audit path of a tree of MAX_BATCH_SIZE leaves, and one spare
MAX_SEQ = 2**63 - 1
KEY_COMMITMENT_DOMAIN = b"AuthROS/key-commitment/v1"

_TEXT_FIELDS = ("owner", "robot", "topic", "type")
_ADDRESS = re.compile(r"0[xX][0-9a-fA-F]{40}")
_LOWER_HEX = re.compile(r"[0-9a-f]*")
_UTC = timedelta(0)
_JSON_ESCAPE = re.compile(rb"\\.", re.DOTALL)
_JSON_STRING = re.compile(rb'"[^"]*"')
_NOT_BRACKETS = bytes(set(range(256)) - set(b"[]{}"))


@dataclass(frozen=True)
class EnvelopeInfo:
    """What can be read from an envelope without its key."""

    version: int
    algorithm: int
    key_id: bytes
    nonce: bytes
    header: dict[str, Any]
    header_bytes: bytes
    ciphertext_length: int  # without the 16-byte tag, so equal to the plaintext length

    @property
    def signer(self) -> str | None:
        """The robot key hash that signed the record (64 hex), None for an unsigned one."""
        return self.header.get("signer")

    @property
    def sig(self) -> str | None:
        """The robot's signature r||s (128 hex), None for an unsigned record."""
        return self.header.get("sig")

    @property
    def provenance(self) -> str:
        """How the record is signed: "v2" (one signature per batch), "v1" (its own) or
        "unsigned"; read from the envelope itself, never from a label beside it."""
        return provenance_format(self.header)


def provenance_format(header: Mapping[str, Any]) -> str:
    """ "v2" for a header with `sig_size`, "v1" for one with `sig` alone, else "unsigned"."""
    if "sig_size" in header:
        return "v2"
    return "v1" if "sig" in header else "unsigned"


def seal(
    key: bytes, header: Mapping[str, Any], plaintext: bytes, *, nonce: bytes | None = None
) -> bytes:
    """Encrypt plaintext under key into an envelope carrying header (authenticated, in clear).

    Leave nonce to chance outside known-answer tests: a nonce used twice with a key breaks GCM.
    """
    envelope_key_id = key_id(key)
    if nonce is None:
        nonce = secrets.token_bytes(NONCE_SIZE)
    elif not isinstance(nonce, bytes) or len(nonce) != NONCE_SIZE:
        raise InvalidKey(f"envelope nonce must be {NONCE_SIZE} bytes")
    header_bytes = _encode_header(header)
    aad = (
        _PREFIX.pack(MAGIC, VERSION, ALG_SM4_GCM, envelope_key_id, nonce, len(header_bytes))
        + header_bytes
    )
    return aad + sm4.gcm_encrypt(key, nonce, plaintext, aad)


def open(
    key: bytes, envelope: bytes, *, info: EnvelopeInfo | None = None
) -> tuple[dict[str, Any], bytes]:
    """Check and decrypt an envelope; return (header, plaintext). `info` is
    read_header(envelope) when the caller read it already (an upload reads each header first),
    so that the header is not parsed and checked twice.

    Raises MalformedEnvelope or UnsupportedEnvelope, then WrongKey, then AuthenticationFailed.
    """
    return OpeningKey(key).open(envelope, info=info)


class OpeningKey:
    """One SM4 key that opens many envelopes (a check run's records of one owner key): its key
    id hashed and its cipher made once, not per envelope. Held only as long as the key itself
    is (a read, a check run), never cached beyond it."""

    __slots__ = ("_cipher", "key_id")

    def __init__(self, key: bytes) -> None:
        self._cipher = sm4.GcmKey(key)
        self.key_id = key_id(key)

    def open(
        self, envelope: bytes, *, info: EnvelopeInfo | None = None
    ) -> tuple[dict[str, Any], bytes]:
        """open(key, envelope, info=info) under this key: the same checks, in the same order."""
        if info is None:
            info = read_header(envelope)
            data = bytes(envelope)
            boundary = PREFIX_SIZE + len(info.header_bytes)
        else:
            data = bytes(envelope)
            boundary = PREFIX_SIZE + len(info.header_bytes)
            _check_info_is_of(info, data, boundary)
        if not hmac.compare_digest(info.key_id, self.key_id):
            raise WrongKey(
                f"envelope was sealed under key id {info.key_id.hex()}, "
                f"but the key given has id {self.key_id.hex()}"
            )
        return info.header, self._cipher.decrypt(info.nonce, data[boundary:], data[:boundary])


def _check_info_is_of(info: EnvelopeInfo, data: bytes, boundary: int) -> None:
    """MalformedEnvelope unless `info` is what read_header read from these very bytes (a few
    comparisons, not a second parse of the header)."""
    if (
        len(data) < boundary + TAG_SIZE
        or _PREFIX.unpack_from(data)[3:] != (info.key_id, info.nonce, len(info.header_bytes))
        or data[PREFIX_SIZE:boundary] != info.header_bytes
    ):
        raise MalformedEnvelope("the header given is not this envelope's")


def read_header(envelope: bytes) -> EnvelopeInfo:
    """Parse and check an envelope's framing and header without decrypting it."""
    if not isinstance(envelope, bytes | bytearray | memoryview):
        raise MalformedEnvelope(f"envelope must be bytes, got {type(envelope).__name__}")
    data = bytes(envelope)
    if data[: len(MAGIC)] != MAGIC:
        raise MalformedEnvelope("not an AuthROS envelope: it does not start with the magic b'AR'")
    if len(data) >= 3 and data[2] != VERSION:
        raise UnsupportedEnvelope(f"envelope version {data[2]} is not supported (only {VERSION})")
    if len(data) >= 4 and data[3] != ALG_SM4_GCM:
        raise UnsupportedEnvelope(
            f"envelope algorithm {data[3]} is not supported (only {ALG_SM4_GCM} = SM4-GCM)"
        )
    if len(data) < MIN_ENVELOPE_SIZE:
        raise MalformedEnvelope(
            f"envelope is truncated: {len(data)} bytes, the minimum is {MIN_ENVELOPE_SIZE}"
        )
    _, version, algorithm, envelope_key_id, nonce, header_length = _PREFIX.unpack_from(data)
    if header_length > MAX_HEADER_LENGTH:
        raise MalformedEnvelope(
            f"envelope header length {header_length} exceeds the limit of {MAX_HEADER_LENGTH}"
        )
    ciphertext_length = len(data) - PREFIX_SIZE - header_length - TAG_SIZE
    if ciphertext_length < 0:
        raise MalformedEnvelope(
            f"envelope is truncated: header length says {header_length} bytes, "
            f"but only {len(data) - PREFIX_SIZE - TAG_SIZE} remain before the tag"
        )
    header_bytes = data[PREFIX_SIZE : PREFIX_SIZE + header_length]
    return EnvelopeInfo(
        version=version,
        algorithm=algorithm,
        key_id=envelope_key_id,
        nonce=nonce,
        header=_decode_header(header_bytes),
        header_bytes=header_bytes,
        ciphertext_length=ciphertext_length,
    )


def digest(envelope: bytes) -> bytes:
    """Return the record digest: SM3 of the envelope bytes (32 bytes)."""
    return sm3_digest(envelope)


def key_id(key: bytes) -> bytes:
    """Return the key id: the first 8 bytes of SM3(key)."""
    return sm3_digest(sm4._check_key(key))[:KEY_ID_SIZE]


def key_commitment(eoa_address: str | bytes, key: bytes) -> bytes:
    """Return SM3("AuthROS/key-commitment/v1" || address (20 bytes) || key) for the chain."""
    return sm3_digest(KEY_COMMITMENT_DOMAIN + _address_bytes(eoa_address) + sm4._check_key(key))


def _address_bytes(eoa_address: str | bytes) -> bytes:
    if isinstance(eoa_address, bytes | bytearray) and len(eoa_address) == 20:
        return bytes(eoa_address)
    if isinstance(eoa_address, str) and _ADDRESS.fullmatch(eoa_address):
        return bytes.fromhex(eoa_address[2:])
    raise InvalidKey("EOA address must be '0x' followed by 40 hex digits, or 20 raw bytes")


def is_lower_hex(value: Any, length: int) -> bool:
    """Whether value is a string of exactly `length` lowercase hex digits."""
    return (
        isinstance(value, str) and len(value) == length and _LOWER_HEX.fullmatch(value) is not None
    )


def canonical_json(header: Mapping[str, Any]) -> bytes:
    """The header's bytes as the envelope carries them: UTF-8 JSON, keys sorted, separators
    `,` `:`, no `\\u` escapes (DESIGN.md "Wire formats"). TypeError or ValueError if it is
    not plain JSON."""
    return _CANONICAL.encode(header).encode("utf-8")


# json.dumps and json.loads with options make an encoder or decoder per call; these are made
# once (both keep no state between calls), each header's check runs both.
_CANONICAL = json.JSONEncoder(
    sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
)


def _encode_header(header: Mapping[str, Any]) -> bytes:
    if not isinstance(header, Mapping):
        raise MalformedEnvelope(f"header must be a mapping, got {type(header).__name__}")
    header = dict(header)
    if not all(isinstance(name, str) for name in header):
        raise MalformedEnvelope("header field names must be strings")
    if _nesting_exceeds(header, MAX_HEADER_DEPTH):
        raise MalformedEnvelope(f"header is nested deeper than {MAX_HEADER_DEPTH} levels")
    try:
        header_bytes = canonical_json(header)
    except (TypeError, ValueError, RecursionError) as exc:
        raise MalformedEnvelope(f"header is not representable as JSON: {exc}") from None
    if len(header_bytes) > MAX_HEADER_LENGTH:
        raise MalformedEnvelope(
            f"header is {len(header_bytes)} bytes as JSON, over the limit of {MAX_HEADER_LENGTH}"
        )
    decoded = _decode_header(header_bytes)
    # so that open() returns exactly the header that was sealed
    if decoded != header:
        raise MalformedEnvelope(
            "header changes in a JSON round trip (use str keys, lists and plain JSON values)"
        )
    return header_bytes


def _decode_header(header_bytes: bytes) -> dict[str, Any]:
    _check_json_depth(header_bytes)
    try:
        header = _HEADER_DECODER.decode(header_bytes.decode("utf-8"))
    except (ValueError, RecursionError):
        raise MalformedEnvelope("envelope header is not valid UTF-8 JSON") from None
    if not isinstance(header, dict):
        raise MalformedEnvelope("envelope header must be a JSON object")
    try:
        canonical = canonical_json(header)
    except (ValueError, RecursionError):
        raise MalformedEnvelope("envelope header is not representable as canonical JSON") from None
    if canonical != header_bytes:
        raise MalformedEnvelope(
            "envelope header is not canonical JSON (sorted keys, no spaces, UTF-8 text)"
        )
    _check_header_fields(header)
    return header


def _nesting_exceeds(value: Any, limit: int) -> bool:
    if isinstance(value, dict):
        children = list(value.values())
    elif isinstance(value, list | tuple):
        children = list(value)
    else:
        return False
    return limit == 0 or any(_nesting_exceeds(child, limit - 1) for child in children)


def _check_json_depth(header_bytes: bytes) -> None:
    # json.loads recurses in C; web3 imports raise the recursion limit to 100000, so a
    # deeply nested header would crash the process instead of raising RecursionError
    if header_bytes.count(b"[") + header_bytes.count(b"{") <= MAX_HEADER_DEPTH:
        return
    # linear time: drop escapes, then strings, and follow the brackets that remain
    outside_strings = _JSON_STRING.sub(b"", _JSON_ESCAPE.sub(b"", header_bytes))
    depth = 0
    for bracket in outside_strings.translate(None, _NOT_BRACKETS):
        depth += 1 if bracket in b"[{" else -1
        if depth > MAX_HEADER_DEPTH:
            raise MalformedEnvelope(
                f"envelope header is nested deeper than {MAX_HEADER_DEPTH} levels"
            )


def _reject_constant(name: str) -> NoReturn:
    raise ValueError(f"{name} is not JSON")


_HEADER_DECODER = json.JSONDecoder(parse_constant=_reject_constant)


def _check_header_fields(header: dict[str, Any]) -> None:
    missing = [name for name in HEADER_FIELDS if name not in header]
    if missing:
        raise MalformedEnvelope(f"envelope header is missing field(s): {', '.join(missing)}")
    for name in _TEXT_FIELDS:
        value = header[name]
        if not isinstance(value, str) or not value:
            raise MalformedEnvelope(f"envelope header field {name!r} must be a non-empty string")
    seq = header["seq"]
    if type(seq) is not int or not 0 <= seq <= MAX_SEQ:
        raise MalformedEnvelope(f"envelope header field 'seq' must be an integer 0..{MAX_SEQ}")
    _check_time(header["time"])
    _check_signature_fields(header)


def _check_signature_fields(header: dict[str, Any]) -> None:
    present = [name for name in SIGNATURE_FIELDS if name in header]
    if present and len(present) != len(SIGNATURE_FIELDS):
        raise MalformedEnvelope(
            f"envelope header fields 'signer' and 'sig' come together, not {present[0]!r} alone"
        )
    for name in present:
        if not is_lower_hex(header[name], SIGNATURE_FIELDS[name]):
            raise MalformedEnvelope(
                f"envelope header field {name!r} must be "
                f"{SIGNATURE_FIELDS[name]} lowercase hex digits"
            )
    if "topic_seq" in header:
        topic_seq = header["topic_seq"]
        if type(topic_seq) is not int or not 0 <= topic_seq <= MAX_SEQ:
            raise MalformedEnvelope(
                f"envelope header field 'topic_seq' must be an integer 0..{MAX_SEQ}"
            )
    batch = [name for name in BATCH_FIELDS if name in header]
    if not batch:
        return
    lacking = [
        name for name in (*BATCH_FIELDS, *SIGNATURE_FIELDS, "topic_seq") if name not in header
    ]
    if lacking:
        raise MalformedEnvelope(
            "a record signed in a batch carries signer, sig, sig_index, sig_size, sig_path "
            f"and topic_seq; this one has no {', '.join(lacking)}"
        )
    size, index, path = header["sig_size"], header["sig_index"], header["sig_path"]
    if type(size) is not int or not 1 <= size <= MAX_BATCH_SIZE:
        raise MalformedEnvelope(
            f"envelope header field 'sig_size' must be an integer 1..{MAX_BATCH_SIZE}"
        )
    if type(index) is not int or not 0 <= index < size:
        raise MalformedEnvelope(
            "envelope header field 'sig_index' must be an integer 0..sig_size-1"
        )
    if (
        not isinstance(path, str)
        or len(path) % 64
        or len(path) > 64 * MAX_BATCH_PATH
        or _LOWER_HEX.fullmatch(path) is None
    ):
        raise MalformedEnvelope(
            "envelope header field 'sig_path' must be lowercase hex, 64 digits per hash"
        )


def _check_time(value: Any) -> None:
    if not isinstance(value, str):
        raise MalformedEnvelope("envelope header field 'time' must be an ISO 8601 UTC string")
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise MalformedEnvelope(
            f"envelope header field 'time' is not ISO 8601: {value[:40]!r}"
        ) from None
    if moment.utcoffset() != _UTC:
        raise MalformedEnvelope(
            f"envelope header field 'time' must be UTC (end in Z or +00:00): {value[:40]!r}"
        )
