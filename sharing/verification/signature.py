"""The facts of a record's robot signature (DESIGN.md "Provenance"), written once for the proof
answer and the export's bundle: the signer and signature its anchored envelope names and the
robot's public key as `04||x||y` lowercase hex, the form authros_verify checks; the proof adds
the key's owner and blocks as the chain holds them. Facts for the reader to check, not a
verdict (the check is sharing.verification.check's)."""

from typing import Any

from chainworker.client import AuthROSChain
from sharing.models import Record
from smcrypto import envelope, sm2


def signature_facts(record: Record, header: dict) -> dict[str, str] | None:
    """The signer, public key and signature of the record, from its envelope's header (as
    read or as opened); None for an unsigned record (a robot added by hand)."""
    signer = header.get("signer")
    if not signer:
        return None
    return {
        "signer": signer,
        "public_key": sm2.public_key_normalize(record.robot.public_key),
        "sig": header.get("sig", ""),
    }


def record_signature(record: Record, data: bytes, client: AuthROSChain) -> dict[str, Any] | None:
    """What a record's proof says of its robot signature: signature_facts of the stored
    envelope, and the key's owner and blocks on chain (robotKeyOf); None for an unsigned
    record."""
    facts = signature_facts(record, envelope.read_header(data).header)
    if facts is None:
        return None
    on_chain = client.robot_key_of(bytes.fromhex(facts["signer"]))
    return {
        **facts,
        "key_owner": on_chain.owner,
        "key_added_block": on_chain.added_block if on_chain.owner else None,
        "key_revoked_block": on_chain.revoked_block,
    }
