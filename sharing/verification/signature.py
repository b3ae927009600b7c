"""The facts of a record's robot signature (DESIGN.md "Provenance"), written once for the proof
answer and the export's bundle: the signer and signature its anchored envelope names and the
robot's public key as `04||x||y` lowercase hex, the form authros_verify checks; the proof adds
the key's owner and blocks as the chain holds them, and for a v2 record (DESIGN.md
"Provenance v2") its place in its batch and the batch root it folds to. Facts for the reader to
check, not a verdict (the check is sharing.verification.check's)."""

from typing import Any

from accounts.models import OwnerKey
from chainworker.client import AuthROSChain
from sharing.models import Record
from sharing.verification.keys import RecordKeys
from smcrypto import CryptoError, envelope, provenance, sm2


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
    envelope, and the key's owner and blocks on chain as the record's owner registered it
    (robotKeyOfOwner: key_owner is the record's owner EOA, or null when that owner never
    registered the key, whoever else did); None for an unsigned record."""
    facts = signature_facts(record, envelope.read_header(data).header)
    if facts is None:
        return None
    on_chain = client.robot_key_of_owner(
        bytes.fromhex(facts["signer"]), owner=record.owner.eoa_address
    )
    return {
        **facts,
        "key_owner": on_chain.owner,
        "key_added_block": on_chain.added_block if on_chain.owner else None,
        "key_revoked_block": on_chain.revoked_block,
    }


def record_batch(record: Record, data: bytes, keys: RecordKeys | None = None) -> dict | None:
    """What a v2 record's proof says of its batch, read from its anchored envelope (never its
    row): `sig_index`, `sig_size`, `sig_path` as its header carries them and `root`, the hex of
    the root its leaf folds to (what the batch's signature is over; the leaf hashes the
    plaintext, so the envelope is opened), null if it does not fold or open. None for a v1 or
    unsigned record."""
    header = envelope.read_header(data).header
    if envelope.provenance_format(header) != "v2":
        return None
    root = None
    try:
        _header, plaintext = envelope.open((keys or RecordKeys()).of(record), data)
        root = provenance.batch_root(header, plaintext).hex()
    except (CryptoError, OwnerKey.DoesNotExist):
        pass
    return {
        "sig_index": header["sig_index"],
        "sig_size": header["sig_size"],
        "sig_path": header["sig_path"],
        "root": root,
        "topic_seq": header["topic_seq"],
    }
