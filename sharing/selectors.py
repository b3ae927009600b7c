"""Reads: which records and grants an owner may see."""

import uuid
from collections.abc import Iterable
from datetime import datetime

from django.db.models import Count, Exists, F, OuterRef, Prefetch, Q, QuerySet, Window
from django.db.models.functions import RowNumber
from django.utils import timezone

from accounts.models import ChainActivity, Owner, OwnerToken, Robot
from core.rows import FixedSelect
from sharing.models import (
    Access,
    AnchorRoot,
    Export,
    Grant,
    GrantChange,
    Record,
    SecurityEvent,
    Verdict,
)
from sharing.selection import RecordSelection
from smcrypto.merkle import path_split


def _unexpired() -> Q:
    return Q(expires_at__isnull=True) | Q(expires_at__gt=timezone.now())


def grant_list_live_received(viewer: Owner) -> QuerySet[Grant]:
    """The grants that let `viewer` read now, in the portal: active and not expired."""
    return Grant.objects.filter(_unexpired(), grantee=viewer, status=Grant.Status.ACTIVE)


def grant_live(*, owner_id: int, viewer: Owner) -> Grant | None:
    """The grant from the owner that lets `viewer` read now, in the portal, if any."""
    return grant_list_live_received(viewer).filter(owner_id=owner_id).first()


def owners_granting(viewer: Owner) -> QuerySet[Owner]:
    """Owners whose grant to `viewer` is active (and not expired) in the portal."""
    return Owner.objects.filter(pk__in=grant_list_live_received(viewer).values("owner_id"))


def record_list_visible_to(viewer: Owner) -> QuerySet[Record]:
    """The viewer's own records and, of owners with a live grant to the viewer, the records
    inside the grant's scope (robots, topics, capture-time window).

    Listing is the portal's view; every read of content is checked on chain again.
    """
    visible = Q(owner=viewer)
    for grant in grant_list_live_received(viewer).only(
        "owner_id", "scope_robots", "scope_topics", "scope_since", "scope_until"
    ):
        visible |= Q(owner_id=grant.owner_id) & grant.scope.as_q()
    return (
        Record.objects.filter(visible)
        .select_related("owner__user", "robot", "deleted_by")
        .order_by("-captured_at", "-seq")
    )


def record_list_owned(owner: Owner) -> QuerySet[Record]:
    return (
        Record.objects.filter(owner=owner)
        .select_related("owner__user", "robot")
        .order_by("-captured_at", "-seq")
    )


def record_list_shared_with(viewer: Owner) -> QuerySet[Record]:
    return record_list_visible_to(viewer).exclude(owner=viewer)


# The record filters' statuses: anchoring's, "tampered" (a view found the stored data
# changed) and "deleted" (tombstones, hidden from lists unless asked for).
RECORD_STATUS_TAMPERED = "tampered"
RECORD_STATUS_DELETED = "deleted"
RECORD_FILTER_STATUSES = [
    *Record.Status.choices,
    (RECORD_STATUS_TAMPERED, "tampered"),
    (RECORD_STATUS_DELETED, "deleted"),
]


def record_list_filtered(
    records: QuerySet[Record],
    *,
    topic: str | None = None,
    data_type: str | None = None,
    status: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
    owner: str | None = None,
    robot: uuid.UUID | str | None = None,
) -> QuerySet[Record]:
    """The records that match every filter given (None or empty: not filtered).

    Capture times are half-open, [since, until); `owner` is a username; `status` is one of
    RECORD_FILTER_STATUSES. Deleted records are left out unless `status` is "deleted". The one
    filter of the record pages and the API.
    """
    if status == RECORD_STATUS_DELETED:
        records = records.filter(deleted_at__isnull=False)
    else:
        records = records.filter(deleted_at__isnull=True)
    records = RecordSelection.from_filters(
        robot=robot, topic=topic, since=since, until=until
    ).apply(records)
    if data_type:
        records = records.filter(data_type=data_type)
    if status == RECORD_STATUS_TAMPERED:
        records = records.filter(tampered_at__isnull=False)
    elif status and status != RECORD_STATUS_DELETED:
        records = records.filter(status=status)
    if owner:
        records = records.filter(owner__user__username=owner)
    return records


# How a record list may be sorted: the `sort` value (a leading "-" for descending) and the
# columns it orders by; capture time and seq break ties, so that pages never overlap.
RECORD_SORTS = {
    "captured": ("captured_at", "seq"),
    "robot": ("robot__name", "captured_at", "seq"),
    "topic": ("topic", "data_type", "captured_at", "seq"),
    "status": ("status", "captured_at", "seq"),
}
RECORD_SORT_DEFAULT = "-captured"


def record_list_sorted(records: QuerySet[Record], sort: str | None) -> QuerySet[Record]:
    """The records in the order `sort` names (RECORD_SORTS, "-" for descending); an unknown
    or empty value is the default, newest capture first."""
    sort = sort or RECORD_SORT_DEFAULT
    descending = sort.startswith("-")
    columns = RECORD_SORTS.get(sort.removeprefix("-"))
    if columns is None:
        return record_list_sorted(records, RECORD_SORT_DEFAULT)
    return records.order_by(*(f"-{column}" if descending else column for column in columns))


def robots_visible_to(viewer: Owner, *, shared: bool) -> QuerySet[Robot]:
    """The robots whose records a record list of the viewer may show: the viewer's own, or
    those with a record inside a live grant to the viewer (robots_in_scope_of)."""
    robots = robots_in_scope_of(viewer) if shared else Robot.objects.filter(owner=viewer)
    return robots.select_related("owner__user").order_by("owner__user__username", "name")


def robots_in_scope_of(viewer: Owner) -> QuerySet[Robot]:
    """Other owners' robots with a record the viewer may read now: inside the scope of a live
    (active, unexpired) grant, by the one selection (record_list_shared_with). A revoked or
    expired grant, or a robot outside a grant's scope, lists nothing (issue 37)."""
    in_scope = record_list_shared_with(viewer).order_by().values("robot_id")
    return Robot.objects.filter(pk__in=in_scope)


def record_counts_of(owner: Owner) -> dict[str, int]:
    """The owner's records not deleted: all, pending, failed and tampered; each one count over
    an index (record_owner_status, record_owner_tampered), never a scan of the records."""
    owned = Record.objects.filter(owner=owner, deleted_at__isnull=True)
    return {
        "total": owned.count(),
        "pending": owned.filter(status=Record.Status.PENDING).count(),
        "failed": owned.filter(status=Record.Status.FAILED).count(),
        "tampered": owned.filter(tampered_at__isnull=False).count(),
    }


def record_list_same_topic(
    viewer: Owner, record: Record, *, since: datetime, until: datetime
) -> QuerySet[Record]:
    """The records of the record's robot, topic and type captured in [since, until) that
    `viewer` may see (their own, or within a live grant's scope: nothing of another robot or
    outside the grant's window), not deleted, oldest first (a gallery's images)."""
    around = RecordSelection(
        robots=(record.robot_id,), topics=(record.topic,), since=since, until=until
    )
    return (
        around.apply(record_list_visible_to(viewer))
        .filter(data_type=record.data_type, deleted_at__isnull=True)
        .order_by("captured_at", "seq")
    )


def record_get_visible(viewer: Owner, record_id: uuid.UUID | str) -> Record | None:
    try:
        record_uuid = uuid.UUID(str(record_id))
    except ValueError:
        return None
    return record_list_visible_to(viewer).filter(pk=record_uuid).first()


def grant_list_given(owner: Owner) -> QuerySet[Grant]:
    return Grant.objects.filter(owner=owner).select_related("grantee__user", "made_with_token")


def grant_list_received(owner: Owner) -> QuerySet[Grant]:
    return Grant.objects.filter(grantee=owner).select_related("owner__user")


# A grant counts, on both sides alike, while it is active or being granted on chain; one being
# revoked does not: its owner has taken it back.
GRANTS_COUNTED = (Grant.Status.ACTIVE, Grant.Status.PENDING)


def grants_described(grants: Iterable[Grant]) -> list[Grant]:
    """The grants, each with `robot_names` (its scope's robots by name, in one query for all),
    for the pages that show what a grant covers."""
    grants = list(grants)
    ids = {robot for grant in grants for robot in grant.scope_robots}
    names = dict(Robot.objects.filter(pk__in=ids).values_list("pk", "name")) if ids else {}
    for grant in grants:
        grant.robot_names = sorted(
            names.get(uuid.UUID(robot), "(removed robot)") for robot in grant.scope_robots
        )
    return grants


def grant_count_given(owner: Owner) -> int:
    return grant_list_given(owner).filter(_unexpired(), status__in=GRANTS_COUNTED).count()


def grant_count_received(owner: Owner) -> int:
    return grant_list_received(owner).filter(_unexpired(), status__in=GRANTS_COUNTED).count()


def grant_topic_choices(owner: Owner, robots: list[Robot]) -> list[str]:
    """Topics a grant of the owner's may name: those of its records and those its robots'
    agents are set up for, sorted."""
    recorded = Record.objects.filter(owner=owner).values_list("topic", flat=True).distinct()
    configured = {entry["name"] for robot in robots for entry in robot.topics}
    return sorted({*recorded, *configured})


def grant_terms_of(owner: Owner, grantee: Owner) -> Grant | None:
    """The owner's grant to `grantee` whose terms may be changed (pending or active)."""
    return Grant.objects.filter(
        owner=owner, grantee=grantee, status__in=[Grant.Status.PENDING, Grant.Status.ACTIVE]
    ).first()


def verdict_latest(record: Record, viewer: Owner) -> Verdict | None:
    """The viewer's most recent integrity verdict on the record (their own views only)."""
    return (
        record.verdicts.filter(access__viewer=viewer, access__checked_by__isnull=True)
        .order_by("-created_at", "-pk")
        .first()
    )


def record_neighbours(record: Record, *, viewer: Owner) -> tuple[Record | None, Record | None]:
    """The records just before and just after it of its robot and topic (by capture time, then
    sequence number) that `viewer` may see and that are not deleted: a record page's previous
    and next. Two seeks in the index record_owner_topic_captured."""
    same = record_list_visible_to(viewer).filter(
        owner_id=record.owner_id,
        robot_id=record.robot_id,
        topic=record.topic,
        data_type=record.data_type,
        deleted_at__isnull=True,
    )
    at, seq = record.captured_at, record.seq
    before = (
        same.filter(captured_at__lte=at)
        .filter(Q(captured_at__lt=at) | Q(seq__lt=seq))
        .order_by("-captured_at", "-seq")
        .first()
    )
    after = (
        same.filter(captured_at__gte=at)
        .filter(Q(captured_at__gt=at) | Q(seq__gt=seq))
        .order_by("captured_at", "seq")
        .first()
    )
    return before, after


def record_position_in(records: QuerySet[Record], record: Record) -> int:
    """How many of `records` (oldest first, as record_list_same_topic) come before `record`."""
    at = record.captured_at
    return records.filter(Q(captured_at__lt=at) | Q(captured_at=at, seq__lt=record.seq)).count()


def record_deletion_text(record: Record) -> str:
    """One line on a deleted record: when, by whom, and what stays."""
    if record.deletion_reason == Record.Deletion.RETENTION:
        who = "by its robot's retention policy"
    elif record.deletion_reason == Record.Deletion.ACCOUNT:
        who = "with its owner's account"
    else:
        who = f"by {record.deleted_by.username}" if record.deleted_by else "by its owner"
    return (
        f"this record was deleted on {record.deleted_at:%Y-%m-%d %H:%M:%S} UTC {who}: its "
        "data is gone; its digest stays on chain and its proof stays available"
    )


def chain_activity_of(owner: Owner) -> QuerySet[ChainActivity]:
    """The owner's transactions as the worker indexed them, and the grants and revocations
    naming the owner as grantee; newest first."""
    return (
        ChainActivity.objects.filter(Q(owner=owner) | Q(counterpart=owner))
        .select_related("owner__user", "counterpart__user")
        .order_by("-at", "-id")
    )


def records_anchored_in(owner: Owner, tx_hashes: list[str], *, per_tx: int) -> list[Record]:
    """The first `per_tx` records of the owner's in each anchoring transaction, in one query."""
    first = Window(
        RowNumber(), partition_by=[F("tx_hash")], order_by=[F("captured_at").asc(), F("seq")]
    )
    return list(
        Record.objects.filter(owner=owner, tx_hash__in=tx_hashes)
        .only("id", "topic", "seq", "tx_hash", "captured_at")
        .annotate(position=first)
        .filter(position__lte=per_tx)
        .order_by("tx_hash", "position")
    )


def chain_backlog() -> dict[str, int]:
    """Records and grants waiting for the chain, and records whose anchoring failed."""
    return {
        "records": Record.objects.filter(status=Record.Status.PENDING).count(),
        "failed_records": Record.objects.filter(status=Record.Status.FAILED).count(),
        "grants": Grant.objects.filter(
            status__in=[Grant.Status.PENDING, Grant.Status.REVOKING]
        ).count(),
    }


def security_events_of(owner: Owner, *, since: datetime | None = None) -> QuerySet[SecurityEvent]:
    """Alarms about the owner's records (tampering, forged uploads), newest first; only
    those since `since` if given."""
    events = SecurityEvent.objects.filter(owner=owner)
    if since is not None:
        events = events.filter(created_at__gte=since)
    return events.select_related("record").order_by("-created_at", "-id")


def grant_list_made_with(token: OwnerToken) -> QuerySet[Grant]:
    """Grants made with an owner API token that can still be revoked (pending or active)."""
    return (
        Grant.objects.filter(
            made_with_token=token, status__in=(Grant.Status.PENDING, Grant.Status.ACTIVE)
        )
        .select_related("owner__user", "grantee__user")
        .order_by("-created_at")
    )


def grant_list_changed_with(token: OwnerToken) -> list[tuple[Grant, dict]]:
    """Live grants (pending or active) not made with `token` whose last change was, each with
    the terms it had before that run of the token's changes (GrantChange.terms_before)."""
    changed = (
        Grant.objects.filter(
            owner_id=token.owner_id,
            status__in=(Grant.Status.PENDING, Grant.Status.ACTIVE),
            changes__token=token,
        )
        .exclude(made_with_token=token)
        .distinct()
        .select_related("owner__user", "grantee__user")
        .order_by("-created_at")
    )
    found = []
    for grant in changed:
        before = None
        for change in grant.changes.order_by("-id"):
            if change.token_id != token.pk or change.kind != GrantChange.Kind.CHANGED:
                break
            before = change.terms_before
        if before is not None:
            found.append((grant, before))
    return found


def record_list_uploaded_by(robot: Robot) -> QuerySet[Record]:
    """What a robot's own token may see: the records that robot uploaded."""
    return record_list_owned(robot.owner).filter(robot=robot)


def record_proof(record: Record, *, chain_id: int, contract: str) -> dict[str, object]:
    """The anchoring proof of an anchored record (DESIGN.md "Anchoring by Merkle roots"), hex
    with 0x: enough for anyone to check the record against the chain without the portal."""
    tree = record.anchor_root
    if tree is not None:
        path = ["0x" + step.hex() for step in path_split(record.merkle_path)]
        mode, index, size, root = "root", record.leaf_index, tree.size, tree.root
        sender, tx, block = tree.sender, tree.tx_hash, tree.block_number
    else:  # records mode: dataQuery holds the digest itself
        path, mode, index, size, root = [], "record", 0, 1, record.digest
        sender, tx, block = record.owner.eoa_address, record.tx_hash, record.block_number
    return {
        "record": str(record.id),
        "owner": record.owner.eoa_address,
        "digest": "0x" + record.digest,
        "mode": mode,
        "leaf_index": index,
        "tree_size": size,
        "path": path,
        "root": "0x" + root,
        "anchor": {
            "chain_id": chain_id,
            "contract": contract,
            "sender": sender,
            "tx": tx,
            "block": block,
        },
    }


# --- the access log: accesses to an owner's records, and an owner's own accesses ------------

# Which views an access log lists: those of the owner's records (by anyone, the owner and the
# operator included), or the owner's own views of records others shared with the owner.
ACCESS_LOG_INCOMING = "incoming"
ACCESS_LOG_OUTGOING = "outgoing"
ACCESS_LOG_DIRECTIONS = [
    (ACCESS_LOG_INCOMING, "views of my data"),
    (ACCESS_LOG_OUTGOING, "my views of data shared with me"),
]


def access_list_access_log(owner: Owner, *, direction: str) -> QuerySet[Access]:
    """The owner's access log as people read it: one row per access (a record page, a gallery
    page, a plot, an export, an operator's check), newest first, with everything a row shows
    in the same query.

    Incoming: every access to the owner's records (Access.record_owner, indexed with the time),
    refused ones included. Outgoing: the owner's own accesses to other owners' records that
    at least one record was granted for (one refused whole would show what a record the viewer
    may not read is; an operator's checks are made with the record owner's rights, so they are
    only ever incoming).
    """
    if direction == ACCESS_LOG_INCOMING:
        accesses = Access.objects.filter(record_owner=owner)
    elif direction == ACCESS_LOG_OUTGOING:
        granted = Verdict.objects.filter(access=OuterRef("pk")).exclude(
            outcome=Verdict.Outcome.NO_ACCESS
        )
        accesses = Access.objects.filter(
            Exists(granted), viewer=owner, checked_by__isnull=True
        ).exclude(record_owner=owner)
    else:
        raise ValueError(f"unknown access log direction {direction!r}")
    return accesses.select_related(
        "viewer__user", "record_owner__user", "record", "robot", "token", "checked_by"
    ).order_by("-created_at", "-id")


def access_list_filtered(
    accesses: QuerySet[Access],
    *,
    viewer: str | None = None,
    owner: str | None = None,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    verdict: str | None = None,
    credential: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> QuerySet[Access]:
    """The accesses that match every filter given (None or empty: not filtered): `viewer` and
    `owner` (the record's) are usernames, `robot` and `topic` those all its records share,
    `verdict` an outcome of any of its records, `credential` a Credential; access times
    half-open, [since, until)."""
    if viewer:
        accesses = accesses.filter(viewer__user__username=viewer)
    if owner:
        accesses = accesses.filter(record_owner__user__username=owner)
    if robot:
        accesses = accesses.filter(robot_id=robot)
    if topic:
        accesses = accesses.filter(topic=topic)
    if verdict:
        found = Verdict.objects.filter(access=OuterRef("pk"), outcome=verdict)
        accesses = accesses.filter(Exists(found))
    if credential:
        accesses = accesses.filter(credential=credential)
    if since is not None:
        accesses = accesses.filter(created_at__gte=since)
    if until is not None:
        accesses = accesses.filter(created_at__lt=until)
    return accesses


def access_log_filter_choices(owner: Owner, *, direction: str) -> dict[str, QuerySet]:
    """What the access log's filters offer, each a small query run only when read: robots
    (id, name, owner's username), topics, and the usernames of the other side (the owner and
    grantees, or the owners who shared with the owner)."""
    if direction == ACCESS_LOG_OUTGOING:
        # Only what the owner's live grants let it read now (their scopes), never the rest of
        # a granting owner's robots and topics, nor those of a revoked or expired grant.
        robots = robots_in_scope_of(owner)
        topics = record_list_shared_with(owner)
        people = owners_granting(owner)
    else:
        robots = Robot.objects.filter(owner=owner)
        topics = Record.objects.filter(owner=owner)
        people = Owner.objects.filter(Q(pk=owner.pk) | Q(grants_received__owner=owner))
    return {
        "robots": robots.order_by("owner__user__username", "name").values_list(
            "id", "name", "owner__user__username"
        ),
        "topics": topics.order_by("topic").values_list("topic", flat=True).distinct(),
        "people": people.order_by("user__username")
        .values_list("user__username", flat=True)
        .distinct(),
    }


def export_list_of(owner: Owner) -> QuerySet[Export]:
    """The owner's exports, newest first (only their requester sees an export)."""
    return Export.objects.filter(requester=owner).order_by("-created_at")


def export_of(owner: Owner, export_id: uuid.UUID | str) -> Export | None:
    try:
        wanted = uuid.UUID(str(export_id))
    except ValueError:
        return None
    return export_list_of(owner).filter(pk=wanted).first()


# --- the reads of every view (written once: core/rows.py) -------------------------------------

_RECORD_TO_OPEN = FixedSelect(
    Record, related=("owner__user", "deleted_by"), where="t0.id = %s", params_of=("id",)
)


# Anchor_root is read whole (its leaves too): one record's tree, not worth a second query.
_RECORD_TO_CHECK = FixedSelect(
    Record, related=("owner", "robot", "anchor_root"), where="t0.id = %s", params_of=("id",)
)


def records_to_check(records: QuerySet[Record]) -> QuerySet[Record]:
    """The records with what the check reads of each: the owner, the robot (a signed record's
    key) and the tree, each read once for all the records that share it (no joins), a tree's
    leaves not at all. For a batch of a read, or an export's."""
    return records.select_related(None).prefetch_related(
        "owner", "robot", Prefetch("anchor_root", AnchorRoot.objects.defer("leaves"))
    )


def record_to_check(record_id: uuid.UUID) -> Record | None:
    """The record the worker checks, with its owner, robot and tree, in one fixed query (the
    view of one record, the most frequent check)."""
    return _RECORD_TO_CHECK.fetch_one(record_id)


def record_to_open(record_id: uuid.UUID) -> Record | None:
    """The record a view opens, with its owner (and user) and who deleted it, if anyone."""
    return _RECORD_TO_OPEN.fetch_one(record_id)


def record_oldest_pending_since() -> datetime | None:
    """When the oldest record still waiting for anchoring was stored (the metrics' backlog
    age); one row of the (status, created_at) index."""
    return (
        Record.objects.filter(status=Record.Status.PENDING)
        .order_by("created_at")
        .values_list("created_at", flat=True)
        .first()
    )


def export_counts_unfinished() -> dict[str, int]:
    """Exports queued and running, by status (the metrics)."""
    unfinished = [Export.Status.QUEUED, Export.Status.RUNNING]
    counts = dict.fromkeys(unfinished, 0)
    rows = (
        Export.objects.filter(status__in=unfinished).values_list("status").annotate(n=Count("id"))
    )
    counts.update(dict(rows))
    return {str(status): count for status, count in counts.items()}
