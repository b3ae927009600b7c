"""Whether a robot signed a record (DESIGN.md "Provenance: robots sign what they capture").

A record is genuine when, beyond its anchoring (authros_verify/anchor.py): the header of its
anchored envelope names `signer` and `sig`; SM3 of the given public key is `signer`; the SM2
signature verifies over the header and the record's plaintext (smcrypto.provenance); and
the record's owner registered the key (`robotKeyOfOwner(owner, signer)`: another owner's
registration of the same key counts for nothing), at or before the record's anchoring block,
and had not revoked it by then. Each failure is an Invalid whose `check` is `signature` or
`robotKeyOf` (the name the check has always been reported under).

Whether a record is signed, and v1 or v2, is read from that header alone (`sig_size` present:
v2, one signature over its upload batch), never from what a bundle or an answer says of it.
A v2 record's leaf folds up its `sig_path` to its batch's root; the SM2 signature over that
root is verified once for all the records of the batch (Signatures).
"""

import re
from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

from authros_verify.chain import ChainReader
from authros_verify.values import Invalid
from smcrypto import provenance
from smcrypto.envelope import provenance_format
from smcrypto.errors import BadSignature, SignatureInvalid

_PUBLIC_KEY = re.compile(r"04[0-9a-f]{128}")
# How many batch signatures a check remembers as verified: the records of one upload batch lie
# close together in an export (capture order), so a few thousand make one SM2 verification per
# batch in bounded memory.
BATCHES_REMEMBERED = 4096


class Signatures:
    """The SM2 verifications of one check: a v1 record's signature is verified for it alone; a
    v2 batch's (the same public key, size, root and `sig` for each of its records) once, its
    outcome remembered for the batch's other records. `verified` counts the verifications."""

    def __init__(self) -> None:
        self.verified = 0
        self._batches: OrderedDict[provenance.SignatureClaim, bool] = OrderedDict()

    def holds(self, claim: provenance.SignatureClaim, *, batch: bool) -> bool:
        if batch and claim in self._batches:
            self._batches.move_to_end(claim)
            return self._batches[claim]
        self.verified += 1
        holds = claim.holds()
        if batch:
            self._batches[claim] = holds
            if len(self._batches) > BATCHES_REMEMBERED:
                self._batches.popitem(last=False)
        return holds


def is_signed(header: Mapping[str, Any]) -> bool:
    """Whether the envelope's header carries a robot signature (`signer` and `sig` come
    together: smcrypto.envelope refuses a header with one alone)."""
    return "signer" in header


def signature_check(
    *,
    header: Mapping[str, Any],
    plaintext: bytes,
    signer: Any,
    sig: Any,
    public_key: Any,
    signatures: Signatures | None = None,
) -> None:
    """The signer, signature and public key stated for a record against the header of its
    anchored envelope and its plaintext (v1 or v2 as that header is); `signatures`, the
    check's verifications so far (a batch's signature verified once)."""
    if not is_signed(header):
        raise Invalid("its envelope carries no robot signature: it is unsigned", check="signature")
    if signer != header["signer"]:
        raise Invalid("its signer is not the one its anchored envelope names", check="signature")
    if sig != header["sig"]:
        raise Invalid("its sig is not the one its anchored envelope carries", check="signature")
    if not isinstance(public_key, str) or not _PUBLIC_KEY.fullmatch(public_key):
        raise Invalid(
            "its public key is not 04 and 128 lowercase hex digits (04||x||y)", check="signature"
        )
    signatures = signatures or Signatures()
    try:
        claim = provenance.signature_claim(public_key, header, plaintext)
        if not signatures.holds(claim, batch=provenance_format(header) == "v2"):
            raise BadSignature("the signature does not verify over this header and plaintext")
    except SignatureInvalid as exc:
        raise Invalid(
            f"its robot signature does not hold ({exc.reason}: {exc})", check="signature"
        ) from None


def robot_key_check(
    chain: ChainReader, *, contract: str, signer: str, owner: str, block: int
) -> None:
    """`owner` registered the key (robotKeyOfOwner), and it was live when the record was
    anchored in `block`."""
    key = chain.robot_key_of_owner(contract, owner, bytes.fromhex(signer))
    if key.owner is None:
        raise Invalid(
            f"its robot key {signer} was never registered on chain by its owner {owner} "
            "(robotKeyOfOwner)",
            check="robotKeyOf",
        )
    if not key.live_at(block):
        when = (
            f"added in block {key.added_block}"
            if key.added_block > block
            else f"revoked in block {key.revoked_block}"
        )
        raise Invalid(
            f"its robot key was not live when it was anchored in block {block} ({when})",
            check="robotKeyOf",
        )
