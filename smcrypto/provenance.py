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

Provenance v2 (DESIGN.md "Provenance v2", fixed) signs a whole upload batch once: each record
is a leaf `SM3(0x00 || "AuthROS/record-signature/v2" || 0x00 || H_i || SM3(plaintext_i))`, `H_i`
the header but `sig`, `sig_index`, `sig_size` and `sig_path` (so `signer` and `topic_seq` are
in it); the leaves make an RFC 9162 tree (smcrypto.merkle's nodes), and `sig` is over
`"AuthROS/batch-signature/v2" || 0x00 || n (8 bytes) || root`. Each record carries its index,
the batch's size and its audit path, so it is checked alone: its leaf folded up its path gives
the root the signature is over. `signature_claim` reads either format into the same claim, and
`claims_hold` verifies each distinct claim once, so a batch costs one SM2 verification.

Pure functions, no Django. `signature_check` says why a signature does not hold with a
SignatureInvalid whose `reason` names the check; `verify_header` is the yes or no;
`signature_claim` does the cheap checks and leaves the SM2 verification to `claims_hold`, which
verifies the signatures of a whole check on every core at once.
"""

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from smcrypto import sm2
from smcrypto.envelope import (
    BATCH_FIELDS,
    MAX_BATCH_SIZE,
    SIGNATURE_FIELDS,
    canonical_json,
    is_lower_hex,
    provenance_format,
)
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
from smcrypto.merkle import InvalidProof, MerkleTree, path_split, root_from_path
from smcrypto.sm3 import DIGEST_SIZE, sm3_digest, sm3_hex

SIGNATURE_DOMAIN = b"AuthROS/record-signature/v1"
BATCH_LEAF_DOMAIN = b"AuthROS/record-signature/v2"
BATCH_SIGNATURE_DOMAIN = b"AuthROS/batch-signature/v2"
# what a v2 leaf leaves out of the header: the batch's signature and the record's place in it
_NOT_IN_LEAF = frozenset({"sig", *BATCH_FIELDS})


@functools.lru_cache(maxsize=256)  # pure; a check names a few robot keys, each per record
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
    signed = {
        name: value
        for name, value in header.items()
        if name not in SIGNATURE_FIELDS and name not in BATCH_FIELDS
    }
    signed["signer"] = key_hash(public_key_hex)
    signed["sig"] = sm2.sign(private_key_hex, signature_message(signed, plaintext))
    return signed


def batch_leaf(header: Mapping[str, Any], plaintext: bytes) -> bytes:
    """A record's leaf in its batch's tree (v2): SM3 of the leaf domain, the canonical JSON
    of every header field but `sig`, `sig_index`, `sig_size` and `sig_path`, and SM3 of the
    plaintext. SignatureMalformed if the header is not plain JSON."""
    if not isinstance(header, Mapping):
        raise SignatureMalformed(f"a header is a mapping, not {type(header).__name__}")
    try:
        header_bytes = canonical_json(
            {name: value for name, value in header.items() if name not in _NOT_IN_LEAF}
        )
    except (TypeError, ValueError, RecursionError) as exc:
        raise SignatureMalformed(f"the header is not plain JSON: {exc}") from None
    if not isinstance(plaintext, bytes | bytearray | memoryview):
        raise InvalidData(f"a record's plaintext is bytes, not {type(plaintext).__name__}")
    return sm3_digest(
        b"\x00" + BATCH_LEAF_DOMAIN + b"\x00" + header_bytes + sm3_digest(bytes(plaintext))
    )


def batch_message(size: int, root: bytes) -> bytes:
    """The bytes a robot signs for a batch of `size` records whose tree has `root` (v2)."""
    return BATCH_SIGNATURE_DOMAIN + b"\x00" + size.to_bytes(8, "big") + bytes(root)


def sign_batch(
    private_key_hex: str,
    public_key_hex: str,
    records: Sequence[tuple[Mapping[str, Any], bytes]],
) -> list[dict[str, Any]]:
    """The headers of a batch of (header, plaintext), in order, signed once as one batch
    (v2): each gains `signer`, `sig`, `sig_index`, `sig_size` and `sig_path` (any it had are
    replaced). Every header must carry its `topic_seq` (the caller's counter). InvalidKey if
    the public key is not the private's; InvalidData for an empty batch or one too large."""
    if sm2.public_key_from_private(private_key_hex) != sm2.public_key_normalize(public_key_hex):
        raise InvalidKey("the SM2 public key given is not the private key's")
    if not 1 <= len(records) <= MAX_BATCH_SIZE:
        raise InvalidData(f"a batch holds 1..{MAX_BATCH_SIZE} records, not {len(records)}")
    signer = key_hash(public_key_hex)
    headers = []
    for header, _plaintext in records:
        if type(header.get("topic_seq")) is not int:
            raise InvalidData("every record of a v2 batch carries its topic_seq (an integer)")
        headers.append(
            {
                **{name: value for name, value in header.items() if name not in _NOT_IN_LEAF},
                "signer": signer,
            }
        )
    tree = MerkleTree(
        [
            batch_leaf(header, plaintext)
            for header, (_, plaintext) in zip(headers, records, strict=True)
        ]
    )
    sig = sm2.sign(private_key_hex, batch_message(tree.size, tree.root))
    for index, header in enumerate(headers):
        header.update(
            sig=sig,
            sig_index=index,
            sig_size=tree.size,
            sig_path=b"".join(tree.path(index)).hex(),
        )
    return headers


def batch_root(header: Mapping[str, Any], plaintext: bytes) -> bytes:
    """The root a v2 record's leaf folds to up its `sig_path` at `sig_index` in a tree of
    `sig_size`: what its batch's signature must be over. SignatureMalformed if the fields are
    not of their shapes or the path cannot fold."""
    size, index, path = header.get("sig_size"), header.get("sig_index"), header.get("sig_path")
    if type(size) is not int or not 1 <= size <= MAX_BATCH_SIZE:
        raise SignatureMalformed(f"'sig_size' must be an integer 1..{MAX_BATCH_SIZE}")
    if type(index) is not int or not 0 <= index < size:
        raise SignatureMalformed("'sig_index' must be an integer 0..sig_size-1")
    if (
        not isinstance(path, str)
        or len(path) % (2 * DIGEST_SIZE)
        or not is_lower_hex(path, len(path))
    ):
        raise SignatureMalformed("'sig_path' must be lowercase hex, 64 digits per hash")
    if type(header.get("topic_seq")) is not int:
        raise SignatureMalformed("a record signed in a batch carries its topic_seq")
    try:
        return root_from_path(
            batch_leaf(header, plaintext), index, size, path_split(bytes.fromhex(path))
        )
    except InvalidProof as exc:
        raise SignatureMalformed(f"its batch path does not fold: {exc}") from None


@dataclass(frozen=True)
class SignatureClaim:
    """A signature whose shape and signer hold, left to verify: the public key, the message
    (signature_message, or for v2 batch_message over the root the record folds to) and `sig`.
    `holds()` verifies it; claims_hold verifies many at once, each distinct claim once (the
    records of one batch make equal claims)."""

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
    JSON, for v2 a place in the batch that does not fold) or SignerMismatch (`signer` is not
    this key's hash). v1 or v2 is read from the header itself (a header with `sig_size` is
    v2), so a v2 record cannot be checked as v1, nor the other way round."""
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
    if provenance_format(header) == "v2":
        message = batch_message(header["sig_size"], batch_root(header, plaintext))
    else:
        message = signature_message(header, plaintext)
    return SignatureClaim(public_key_hex, message, header["sig"])


def claims_hold(claims: Sequence[SignatureClaim]) -> list[bool]:
    """Whether each claim's signature verifies, in order: each distinct claim verified once
    (the records of one v2 batch make one), on every core (sm2.verify_many), for the records
    of one check or one export batch."""
    distinct = list(dict.fromkeys(claims))
    verified = sm2.verify_many([(claim.public_key, claim.message, claim.sig) for claim in distinct])
    holds = dict(zip(distinct, verified, strict=True))
    return [holds[claim] for claim in claims]


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
