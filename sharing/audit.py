"""The owner's audit trail as the audit page lists it, read from the database's index of the
owner's transactions (accounts.models.ChainActivity), never from the chain's logs.

The worker writes one row per transaction when it sees the receipt: registration steps, key
rotations, anchoring batches, grants and revocations (the grantee sees those too). Here the
rows of one page become entries with titles, and an anchoring entry lists its first records.
"""

import uuid
from dataclasses import dataclass, field
from datetime import datetime

from django.core.paginator import Page, Paginator
from django.db.models import Exists, OuterRef

from accounts.models import ChainActivity, Owner
from sharing.models import Record
from sharing.selectors import chain_activity_of, records_anchored_in

# Records listed under one anchoring transaction; the rest are counted.
AUDIT_RECORDS_PER_UPLOAD = 10

Kind = ChainActivity.Kind
_TITLES = {
    Kind.FUNDED: "EOA funded by the portal operator",
    Kind.ENROLLED: "Enrolled in the AuthROS contract by the portal operator",
    Kind.REGISTERED: "Registered the key commitment",
    Kind.KEY_ROTATED: "Rotated the key",
}


@dataclass
class AuditEntry:
    at: datetime
    block_number: int | None
    tx_hash: str
    kind: str
    title: str
    detail: str = ""
    records: list[Record] = field(default_factory=list)
    more_records: int = 0


def audit_page_of_owner(
    owner: Owner,
    *,
    page: object,
    per_page: int,
    kind: str | None = None,
    robot: uuid.UUID | str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> Page:
    """One page of the owner's audit trail, newest first; its object_list holds AuditEntry.

    Filtered by `kind` (a ChainActivity kind), `robot` (the anchoring transactions holding a
    record of that robot of the owner's) and the half-open period [since, until) of the
    receipts, all in the page's one query. A page past the last is the last page, as
    Paginator.get_page gives it.
    """
    activity = chain_activity_of(owner)
    if kind:
        activity = activity.filter(kind=kind)
    if robot:
        # An activity row names no robot: its anchoring transaction's records do.
        of_robot = Record.objects.filter(owner=owner, robot_id=robot, tx_hash=OuterRef("tx_hash"))
        activity = activity.filter(Exists(of_robot), owner=owner, kind=Kind.ANCHORED)
    if since is not None:
        activity = activity.filter(at__gte=since)
    if until is not None:
        activity = activity.filter(at__lt=until)
    found = Paginator(activity, per_page).get_page(page)
    found.object_list = audit_entries(owner, list(found.object_list))
    return found


def audit_entries(owner: Owner, activity: list[ChainActivity]) -> list[AuditEntry]:
    """Entries of `activity` as `owner` sees them, in the same order; the records of every
    anchoring transaction among them are read in one query."""
    anchored = [row.tx_hash for row in activity if row.kind == Kind.ANCHORED]
    listed: dict[str, list[Record]] = {}
    if anchored:
        for record in records_anchored_in(owner, anchored, per_tx=AUDIT_RECORDS_PER_UPLOAD):
            listed.setdefault(record.tx_hash, []).append(record)
    return [_entry(owner, row, listed.get(row.tx_hash, [])) for row in activity]


def _entry(owner: Owner, row: ChainActivity, records: list[Record]) -> AuditEntry:
    entry = AuditEntry(row.at, row.block_number, row.tx_hash, row.kind, _TITLES.get(row.kind, ""))
    detail = row.detail if isinstance(row.detail, dict) else {}
    if row.kind in (Kind.REGISTERED, Kind.KEY_ROTATED) and detail.get("key_id"):
        entry.detail = f"key {detail['key_id']}, commitment {detail.get('commitment', '-')}"
    elif row.kind == Kind.ANCHORED:
        count = row.record_count
        entry.kind = "upload"
        entry.title = f"Anchored {count} record{'s' if count != 1 else ''}"
        entry.records = records
        entry.more_records = max(count - len(records), 0)
    elif row.kind in (Kind.GRANTED, Kind.REVOKED):
        granted = row.kind == Kind.GRANTED
        if row.owner_id == owner.pk:
            other = row.counterpart.username if row.counterpart else "a former owner"
            entry.title = f"{'Granted' if granted else 'Revoked'} access to {other}"
            entry.kind = "grant-given" if granted else "revoke-given"
        else:
            verb = "granted you" if granted else "revoked your"
            entry.title = f"{row.owner.username} {verb} access"
            entry.kind = "grant-received" if granted else "revoke-received"
    return entry
