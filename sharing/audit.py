"""The owner's audit trail as the audit page lists it, read from the database's index of the
owner's transactions (accounts.models.ChainActivity), never from the chain's logs.

The worker writes one row per transaction when it sees the receipt: registration steps, key
rotations, robots' keys added and revoked (from the receipt's RobotKeyAdded and RobotKeyRevoked
events), anchoring batches, grants and revocations (the grantee sees those too). The page
lists the few that change who may read what first (grants, revocations, keys, registration),
then the anchoring, grouped per minute: a robot anchoring once a second makes one line a
minute ("Anchored 720 records in 12:04 (UTC)"), not sixty, each naming its transactions and
its first records.
"""

import uuid
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from django.core.paginator import Page, Paginator
from django.db.models import Count, Exists, Max, Min, OuterRef, QuerySet, Sum
from django.db.models.functions import TruncMinute

from accounts.models import ChainActivity, Owner
from sharing.models import Record
from sharing.selectors.activity import chain_activity_of, records_anchored_in

# Records listed under one minute of anchoring; the rest are counted.
AUDIT_RECORDS_PER_UPLOAD = 10
# Transactions named under one minute of anchoring; the rest are counted.
AUDIT_TRANSACTIONS_PER_MINUTE = 3
# Grants, revocations and key changes listed on top; older ones through the kind filter.
AUDIT_ACCOUNT_ENTRIES = 50

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
    # A minute of anchoring: its transactions (the first few) and how many are not named.
    transactions: list[str] = field(default_factory=list)
    more_transactions: int = 0
    last_block: int | None = None


@dataclass
class AuditTrail:
    """The page: grants, revocations and key changes first (the newest AUDIT_ACCOUNT_ENTRIES,
    and how many more), then one page of anchoring, a minute an entry (`anchoring`, a Page
    of AuditEntry)."""

    account: list[AuditEntry]
    account_more: int
    anchoring: Page


def audit_page_of_owner(
    owner: Owner,
    *,
    page: object,
    per_page: int,
    kind: str | None = None,
    robot: uuid.UUID | str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> AuditTrail:
    """The owner's audit trail, newest first, `per_page` minutes of anchoring a page.

    Filtered by `kind` (a ChainActivity kind), `robot` (the anchoring transactions holding a
    record of that robot of the owner's; nothing else names a robot) and the half-open period
    [since, until) of the receipts. A page past the last is the last page, as
    Paginator.get_page gives it.
    """
    activity = chain_activity_of(owner)
    if kind:
        activity = activity.filter(kind=kind)
    if since is not None:
        activity = activity.filter(at__gte=since)
    if until is not None:
        activity = activity.filter(at__lt=until)
    account_rows = activity.exclude(kind=Kind.ANCHORED)
    anchored = activity.filter(owner=owner, kind=Kind.ANCHORED)
    if robot:
        # An activity row names no robot: its anchoring transaction's records do.
        of_robot = Record.objects.filter(owner=owner, robot_id=robot, tx_hash=OuterRef("tx_hash"))
        anchored = anchored.filter(Exists(of_robot))
        account_rows = account_rows.none()
    shown = list(account_rows[: AUDIT_ACCOUNT_ENTRIES + 1])
    account = [_entry(owner, row) for row in shown[:AUDIT_ACCOUNT_ENTRIES]]
    account_more = account_rows.count() - AUDIT_ACCOUNT_ENTRIES if len(shown) > len(account) else 0
    minutes = (
        anchored.annotate(minute=TruncMinute("at"))
        .order_by()
        .values("minute")
        .annotate(
            records=Sum("record_count"),
            transactions=Count("id"),
            first_block=Min("block_number"),
            last_block=Max("block_number"),
        )
        .order_by("-minute")
    )
    found = Paginator(minutes, per_page).get_page(page)
    found.object_list = _anchoring_entries(owner, anchored, list(found.object_list))
    return AuditTrail(account, account_more, found)


def _anchoring_entries(
    owner: Owner, anchored: QuerySet[ChainActivity], minutes: list[dict]
) -> list[AuditEntry]:
    """One entry per minute of the page, with its transactions (one query for the page) and
    the first records of its first transactions (one more)."""
    if not minutes:
        return []
    start = minutes[-1]["minute"]
    end = minutes[0]["minute"] + timedelta(minutes=1)
    rows = (
        anchored.filter(at__gte=start, at__lt=end)
        .select_related(None)
        .only("tx_hash", "at", "record_count")
    )
    per_minute: dict[datetime, list[ChainActivity]] = {}
    for row in rows.order_by("at", "id"):
        per_minute.setdefault(_minute_of(row.at), []).append(row)
    named = {minute: txs[:AUDIT_TRANSACTIONS_PER_MINUTE] for minute, txs in per_minute.items()}
    listed: dict[str, list[Record]] = {}
    hashes = [row.tx_hash for rows_ in named.values() for row in rows_]
    if hashes:
        for record in records_anchored_in(owner, hashes, per_tx=AUDIT_RECORDS_PER_UPLOAD):
            listed.setdefault(record.tx_hash, []).append(record)
    entries = []
    for group in minutes:
        txs = named.get(group["minute"], [])
        records = [r for row in txs for r in listed.get(row.tx_hash, [])]
        records = records[:AUDIT_RECORDS_PER_UPLOAD]
        count = group["records"] or 0
        entries.append(
            AuditEntry(
                at=group["minute"],
                block_number=group["first_block"],
                tx_hash=txs[0].tx_hash if txs else "",
                kind="upload",
                title=(
                    f"Anchored {count} record{'s' if count != 1 else ''} in "
                    f"{group['minute']:%H:%M} (UTC)"
                ),
                records=records,
                more_records=max(count - len(records), 0),
                transactions=[row.tx_hash for row in txs],
                more_transactions=max(group["transactions"] - len(txs), 0),
                last_block=group["last_block"],
            )
        )
    return entries


def _minute_of(moment: datetime) -> datetime:
    return moment.replace(second=0, microsecond=0)


def _entry(owner: Owner, row: ChainActivity) -> AuditEntry:
    entry = AuditEntry(row.at, row.block_number, row.tx_hash, row.kind, _TITLES.get(row.kind, ""))
    detail = row.detail if isinstance(row.detail, dict) else {}
    if row.kind in (Kind.REGISTERED, Kind.KEY_ROTATED) and detail.get("key_id"):
        entry.detail = f"key {detail['key_id']}, commitment {detail.get('commitment', '-')}"
    elif row.kind in (Kind.ROBOT_KEY_ADDED, Kind.ROBOT_KEY_REVOKED):
        added = row.kind == Kind.ROBOT_KEY_ADDED
        robot = detail.get("robot") or "a robot"
        entry.title = (
            f"Registered the signing key of robot {robot}"
            if added
            else f"Revoked the signing key of robot {robot}"
        )
        entry.kind = "robot-key-added" if added else "robot-key-revoked"
        entry.detail = f"key hash {detail.get('key_hash', '-')}"
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
