"""Whether a robot signed a record (DESIGN.md "Provenance: robots sign what they capture").

A record is genuine when, beyond its anchoring (authros_verify/anchor.py): the header of its
anchored envelope names `signer` and `sig`; SM3 of the given public key is `signer`; the SM2
signature verifies over the header and the record's plaintext (smcrypto.provenance); and
`robotKeyOf(signer)` names the record's owner, added at or before the record's anchoring block
and not revoked by then. Each failure is an Invalid whose `check` is `signature` or
`robotKeyOf`.
"""

import re
from collections.abc import Mapping
from typing import Any

from authros_verify.chain import ChainReader
from authros_verify.values import Invalid
from smcrypto import provenance
from smcrypto.errors import SignatureInvalid

_PUBLIC_KEY = re.compile(r"04[0-9a-f]{128}")


def is_signed(header: Mapping[str, Any]) -> bool:
    """Whether the envelope's header carries a robot signature (`signer` and `sig` come
    together: smcrypto.envelope refuses a header with one alone)."""
    return "signer" in header


def signature_check(
    *, header: Mapping[str, Any], plaintext: bytes, signer: Any, sig: Any, public_key: Any
) -> None:
    """The signer, signature and public key stated for a record against the header of its
    anchored envelope and its plaintext."""
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
    try:
        provenance.signature_check(public_key, header, plaintext)
    except SignatureInvalid as exc:
        raise Invalid(
            f"its robot signature does not hold ({exc.reason}: {exc})", check="signature"
        ) from None


def robot_key_check(
    chain: ChainReader, *, contract: str, signer: str, owner: str, block: int
) -> None:
    """robotKeyOf(signer) names `owner`, and the key was live when the record was anchored
    in `block`."""
    key = chain.robot_key_of(contract, bytes.fromhex(signer))
    if key.owner is None:
        raise Invalid(
            f"its robot key {signer} was never registered on chain (robotKeyOf names no owner)",
            check="robotKeyOf",
        )
    if key.owner.lower() != owner.lower():
        raise Invalid(
            f"its robot key is registered on chain by {key.owner}, not by its owner {owner}",
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
