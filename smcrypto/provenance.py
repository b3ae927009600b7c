"""A robot's signature over what it captured (DESIGN.md "Provenance: robots sign what they
capture", fixed).

A paired robot signs every envelope it seals with its SM2 pairing key, so that anyone holding
a record's plaintext and the robot's public key (registered on chain, `robotKeyOf`) can check,
without the portal and without the owner's key, that this robot captured exactly this. Two
header fields carry the signature, authenticated by the envelope like every other field:

- `signer`: SM3 of the robot's public key `x||y` (64 bytes), 64 lowercase hex (`key_hash`);
- `sig`: the SM2 signature `r||s`, 128 lowercase hex (GB/T 32918.2 with SM3 and the default
  ID `1234567812345678`), over
  `M = "AuthROS/record-signature/v1" || 0x00 || H || SM3(plaintext)`, where `H` is the header
  of every field except `sig` (so `signer` is in it) in the envelope's own canonical JSON.

Pure functions, no Django. `signature_check` says why a signature does not hold with a
SignatureInvalid whose `reason` names the check; `verify_header` is the yes or no;
`signature_claim` does the cheap checks and leaves the SM2 verification to `claims_hold`, which
verifies the signatures of a whole check on every core at once.
"""

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from smcrypto import sm2
from smcrypto.envelope import SIGNATURE_FIELDS, canonical_json, is_lower_hex
from smcrypto.errors import (
    BadSignature,
    CryptoError,
    InvalidData,
    InvalidKey,
    SignatureInvalid,
    SignatureMalformed,
    SignatureMissing,
    SignerMismatch,
)
from smcrypto.sm3 import sm3_digest, sm3_hex

SIGNATURE_DOMAIN = b"AuthROS/record-signature/v1"


def key_hash(public_key_hex: str) -> str:
    """A robot key's hash, the `signer` of its records: SM3 of `x||y` as 64 lowercase hex.
    Takes `04||x||y` or `x||y`; InvalidKey if it is not a point on the SM2 curve."""
    return sm3_hex(bytes.fromhex(sm2.public_key_normalize(public_key_hex)[2:]))


def signature_message(header: Mapping[str, Any], plaintext: bytes) -> bytes:
    """The bytes a robot signs: the domain, 0x00, the canonical JSON of every header field
    but `sig`, and SM3 of the plaintext. SignatureMalformed if the header is not plain JSON."""
    if not isinstance(header, Mapping):
        raise SignatureMalformed(f"a header is a mapping, not {type(header).__name__}")
    try:
        header_bytes = canonical_json(
            {name: value for name, value in header.items() if name != "sig"}
        )
    except (TypeError, ValueError, RecursionError) as exc:
        raise SignatureMalformed(f"the header is not plain JSON: {exc}") from None
    if not isinstance(plaintext, bytes | bytearray | memoryview):
        raise InvalidData(f"a record's plaintext is bytes, not {type(plaintext).__name__}")
    return SIGNATURE_DOMAIN + b"\x00" + header_bytes + sm3_digest(bytes(plaintext))


def sign_header(
    private_key_hex: str, public_key_hex: str, header: Mapping[str, Any], plaintext: bytes
) -> dict[str, Any]:
    """The header with `signer` and `sig` added (any it had are replaced), signed over the
    plaintext with the robot's key pair. InvalidKey if the public key is not the private's."""
    if sm2.public_key_from_private(private_key_hex) != sm2.public_key_normalize(public_key_hex):
        raise InvalidKey("the SM2 public key given is not the private key's")
    signed = {name: value for name, value in header.items() if name not in SIGNATURE_FIELDS}
    signed["signer"] = key_hash(public_key_hex)
    signed["sig"] = sm2.sign(private_key_hex, signature_message(signed, plaintext))
    return signed


@dataclass(frozen=True)
class SignatureClaim:
    """A signature whose shape and signer hold, left to verify: the public key, the message
    (signature_message) and `sig`. `holds()` verifies it; claims_hold verifies many at once."""

    public_key: str
    message: bytes
    sig: str

    def holds(self) -> bool:
        return sm2.verify(self.public_key, self.message, self.sig)


def signature_claim(
    public_key_hex: str, header: Mapping[str, Any], plaintext: bytes
) -> SignatureClaim:
    """What verifying the robot's signature over this header and plaintext takes, once the
    cheap checks hold. Raises SignatureMissing (no `signer` or `sig`), SignatureMalformed (not
    lowercase hex of their lengths, a public key that is not an SM2 point, a header that is not
    JSON) or SignerMismatch (`signer` is not this key's hash)."""
    if not isinstance(header, Mapping):
        raise SignatureMalformed(f"a header is a mapping, not {type(header).__name__}")
    missing = [name for name in SIGNATURE_FIELDS if name not in header]
    if missing:
        raise SignatureMissing(f"the header has no {' and no '.join(missing)}: it is unsigned")
    for name, length in SIGNATURE_FIELDS.items():
        if not is_lower_hex(header[name], length):
            raise SignatureMalformed(f"{name!r} must be {length} lowercase hex digits")
    try:
        expected_signer = key_hash(public_key_hex)
    except CryptoError as exc:
        raise SignatureMalformed(f"the robot's public key is not usable: {exc}") from None
    if header["signer"] != expected_signer:
        raise SignerMismatch(
            f"the record names signer {header['signer']}, not this key's hash {expected_signer}"
        )
    return SignatureClaim(public_key_hex, signature_message(header, plaintext), header["sig"])


def claims_hold(claims: Sequence[SignatureClaim]) -> list[bool]:
    """Whether each claim's signature verifies, in order: on every core (sm2.verify_many), for
    the records of one check or one export batch."""
    return sm2.verify_many([(claim.public_key, claim.message, claim.sig) for claim in claims])


def signature_check(public_key_hex: str, header: Mapping[str, Any], plaintext: bytes) -> None:
    """Check that the robot whose public key is given signed this header and plaintext.

    Raises what signature_claim raises, or BadSignature.
    """
    if not signature_claim(public_key_hex, header, plaintext).holds():
        raise BadSignature("the signature does not verify over this header and plaintext")


def verify_header(public_key_hex: str, header: Mapping[str, Any], plaintext: bytes) -> bool:
    """Whether the robot whose public key is given signed this header and plaintext."""
    try:
        signature_check(public_key_hex, header, plaintext)
    except SignatureInvalid:
        return False
    return True
