"""Reads of records: what a viewer may see (their own, and what live grants cover), the
record lists' filters and sorts, a record page's neighbours and proof, and the fixed reads of
the records a view opens and the worker checks (core/rows.py).

Listing is the portal's view; every read of content is checked on chain again
(sharing/verification/)."""

import uuid
from collections.abc import Sequence
from datetime import datetime

from django.db.models import Prefetch, Q, QuerySet

from accounts.models import Owner, Robot
from core.rows import FixedSelect, instances_made
from sharing.models import AnchorRoot, Record
from sharing.selection import RecordSelection
from sharing.selectors.grants import grant_list_live_received
from smcrypto.merkle import path_split


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
        records = records.live()
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
# columns it orders by; capture time and seq break ties, so that pages never overlap (capture
# order itself is (captured_at, id), as its pages' cursors: sharing/selectors/record_pages.py).
RECORD_SORTS = {
    "captured": ("captured_at", "id"),
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
    owned = Record.objects.filter(owner=owner).live()
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
        .filter(data_type=record.data_type)
        .live()
        .order_by("captured_at", "seq")
    )


def record_get_visible(viewer: Owner, record_id: uuid.UUID | str) -> Record | None:
    try:
        record_uuid = uuid.UUID(str(record_id))
    except ValueError:
        return None
    return record_list_visible_to(viewer).filter(pk=record_uuid).first()


def record_neighbours(record: Record, *, viewer: Owner) -> tuple[Record | None, Record | None]:
    """The records just before and just after it of its robot and topic (by capture time, then
    sequence number) that `viewer` may see and that are not deleted: a record page's previous
    and next. Two seeks in the index record_owner_topic_captured."""
    same = (
        record_list_visible_to(viewer)
        .filter(
            owner_id=record.owner_id,
            robot_id=record.robot_id,
            topic=record.topic,
            data_type=record.data_type,
        )
        .live()
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


# --- the reads of every view (written once: core/rows.py) -------------------------------------

_RECORD_TO_OPEN = FixedSelect(
    Record, related=("owner__user", "deleted_by"), where="t0.id = %s", params_of=("id",)
)


def records_to_check(records: QuerySet[Record]) -> QuerySet[Record]:
    """The records with what the check reads of each: the owner, the robot (a signed record's
    key) and the tree, each read once for all the records that share it (no joins), a tree's
    leaves not at all. For a batch of a read, or an export's."""
    return records.select_related(None).prefetch_related(
        "owner", "robot", Prefetch("anchor_root", AnchorRoot.objects.defer("leaves"))
    )


# What the worker's check reads of a record's row (sharing/verification/check.py: access,
# the stored envelope and its key, the tree and the path, the signature's row facts, its tamper
# answer; a series' capture time): the other columns are not read for a check.
_CHECKED_COLUMNS = (
    "id",
    "owner_id",
    "robot_id",
    "topic",
    "seq",
    "captured_at",
    "key_id",
    "digest",
    "signer",
    "topic_seq",
    "storage_name",
    "status",
    "block_number",
    "anchor_root_id",
    "leaf_index",
    "merkle_path",
    "deleted_at",
)


_CHECKED_ATTNAMES = [Record._meta.get_field(name).attname for name in _CHECKED_COLUMNS]


def records_to_check_by_id(record_ids: Sequence[uuid.UUID]) -> list[Record]:
    """The records of these ids that exist, in the order asked, with what the check reads:
    only the check's columns of each row, and its owner, robot and tree (without its leaves)
    each read once for all the records that share it, set on the records directly (the
    queryset's prefetch machinery per record cost more than the rows: bench/REPORT.md). The
    rows are read as tuples (with the ORM's converters) and made instances without
    Model.__init__'s per-field work (core.rows.instances_made); the columns not read are
    deferred, as `only()` leaves them."""
    rows = Record.objects.filter(pk__in=record_ids).values_list(*_CHECKED_ATTNAMES)
    found = {
        record.pk: record
        for record in instances_made(Record, _CHECKED_ATTNAMES, list(rows), alias=rows.db)
    }
    records = [found[record_id] for record_id in record_ids if record_id in found]
    owners = Owner.objects.in_bulk({record.owner_id for record in records})
    robots = Robot.objects.in_bulk({record.robot_id for record in records})
    trees = AnchorRoot.objects.defer("leaves").in_bulk(
        {record.anchor_root_id for record in records} - {None}
    )
    for record in records:
        _OWNER.set_cached_value(record, owners[record.owner_id])
        _ROBOT.set_cached_value(record, robots[record.robot_id])
        _TREE.set_cached_value(record, trees.get(record.anchor_root_id))
    return records


_OWNER, _ROBOT, _TREE = (Record._meta.get_field(name) for name in ("owner", "robot", "anchor_root"))


def record_to_open(record_id: uuid.UUID) -> Record | None:
    """The record a view opens, with its owner (and user) and who deleted it, if anyone."""
    return _RECORD_TO_OPEN.fetch_one(record_id)
