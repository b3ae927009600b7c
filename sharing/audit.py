"""The owner's audit trail as the audit page lists it, read from the contract's events.

Events are decoded here (names for addresses, record ids for bytes32, the uploads of one
transaction grouped), so the page only paginates and renders.
"""

from dataclasses import dataclass, field

from accounts.models import Owner
from chainworker.chain import ChainEvent, bytes32_to_record_id
from sharing.models import Record
from sharing.selectors import chain_events_of_owner, owners_by_address

# Record ids listed under one upload transaction; the rest are counted.
AUDIT_RECORDS_PER_UPLOAD = 10


@dataclass
class AuditEntry:
    block_number: int
    tx_hash: str
    kind: str
    title: str
    detail: str = ""
    records: list[tuple[str, Record | None]] = field(default_factory=list)
    more_records: int = 0


def audit_entries_of_owner(owner: Owner) -> list[AuditEntry]:
    """The owner's events on chain, newest first; the uploads of one transaction are one entry.

    Raises chainworker.chain.ChainError when the chain cannot be read.
    """
    return audit_entries_from_events(owner, chain_events_of_owner(owner))


def audit_entries_from_events(owner: Owner, events: list[ChainEvent]) -> list[AuditEntry]:
    """Entries of `events` (oldest first, as the chain gives them), newest first."""
    names = owners_by_address(
        [str(e.args[arg]) for e in events for arg in ("owner", "grantee") if arg in e.args]
    )

    def who(address: object) -> str:
        found = names.get(str(address).lower())
        return found.username if found else str(address)

    me = owner.eoa_address.lower()
    entries: list[AuditEntry] = []
    uploads: dict[str, AuditEntry] = {}
    upload_ids: dict[str, list[str]] = {}
    for event in events:
        args = event.args
        if event.name == "DataUploaded":
            entry = uploads.get(event.tx_hash)
            if entry is None:
                entry = AuditEntry(event.block_number, event.tx_hash, "upload", "")
                uploads[event.tx_hash] = entry
                upload_ids[event.tx_hash] = []
                entries.append(entry)
            upload_ids[event.tx_hash].append(str(bytes32_to_record_id(args["id"])))
            continue
        entry = AuditEntry(event.block_number, event.tx_hash, event.name, "")
        if event.name == "Enrolled":
            entry.title = "Enrolled in the AuthROS contract by the portal operator"
        elif event.name == "Registered":
            entry.title = "Registered the key commitment"
            entry.detail = "0x" + bytes(args["commitment"]).hex()
        elif event.name == "KeyRotated":
            entry.title = "Rotated the key"
            entry.detail = (
                f"0x{bytes(args['oldCommitment']).hex()} → 0x{bytes(args['newCommitment']).hex()}"
            )
        elif event.name in ("AuthorityGranted", "AuthorityRevoked"):
            granted = event.name == "AuthorityGranted"
            if str(args["owner"]).lower() == me:
                verb = "Granted" if granted else "Revoked"
                entry.title = f"{verb} access to {who(args['grantee'])}"
                entry.kind = "grant-given" if granted else "revoke-given"
            else:
                verb = "granted you" if granted else "revoked your"
                entry.title = f"{who(args['owner'])} {verb} access"
                entry.kind = "grant-received" if granted else "revoke-received"
        entries.append(entry)
    known = {
        str(record.pk): record
        for record in Record.objects.filter(
            owner=owner, pk__in=[i for ids in upload_ids.values() for i in ids]
        )
    }
    for tx_hash, ids in upload_ids.items():
        entry = uploads[tx_hash]
        entry.title = f"Anchored {len(ids)} record{'s' if len(ids) != 1 else ''}"
        entry.records = [(i, known.get(i)) for i in ids[:AUDIT_RECORDS_PER_UPLOAD]]
        entry.more_records = max(len(ids) - AUDIT_RECORDS_PER_UPLOAD, 0)
    entries.reverse()
    return entries
