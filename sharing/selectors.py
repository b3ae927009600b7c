"""Reads: which records and grants an owner may see."""

import uuid
from datetime import datetime

from django.db.models import F, Q, QuerySet, Window
from django.db.models.functions import RowNumber

from accounts.models import ChainActivity, Owner, OwnerToken, Robot
from sharing.models import Grant, Record, SecurityEvent, Verdict
from smcrypto.merkle import path_split


def owners_granting(viewer: Owner) -> QuerySet[Owner]:
    """Owners whose grant to `viewer` is active in the portal."""
    return Owner.objects.filter(
        grants_given__grantee=viewer, grants_given__status=Grant.Status.ACTIVE
    )


def record_list_visible_to(viewer: Owner) -> QuerySet[Record]:
    """The viewer's own records and those of owners with an active grant to the viewer.

    Listing is the portal's view; every read of content is checked on chain again.
    """
    granting = Grant.objects.filter(grantee=viewer, status=Grant.Status.ACTIVE).values("owner_id")
    return (
        Record.objects.filter(Q(owner=viewer) | Q(owner_id__in=granting))
        .select_related("owner__user", "robot")
        .order_by("-captured_at", "-seq")
    )


def record_list_owned(owner: Owner) -> QuerySet[Record]:
    return record_list_visible_to(owner).filter(owner=owner)


def record_list_shared_with(viewer: Owner) -> QuerySet[Record]:
    return record_list_visible_to(viewer).exclude(owner=viewer)


# The record filters' statuses: anchoring's, and "tampered" (a view found the stored data
# changed), which is not an anchoring status.
RECORD_STATUS_TAMPERED = "tampered"
RECORD_FILTER_STATUSES = [*Record.Status.choices, (RECORD_STATUS_TAMPERED, "tampered")]


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
    RECORD_FILTER_STATUSES. The one filter of the record pages and the API.
    """
    if topic:
        records = records.filter(topic=topic)
    if data_type:
        records = records.filter(data_type=data_type)
    if status == RECORD_STATUS_TAMPERED:
        records = records.filter(tampered_at__isnull=False)
    elif status:
        records = records.filter(status=status)
    if since is not None:
        records = records.filter(captured_at__gte=since)
    if until is not None:
        records = records.filter(captured_at__lt=until)
    if owner:
        records = records.filter(owner__user__username=owner)
    if robot:
        records = records.filter(robot_id=robot)
    return records


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


def grant_count_given(owner: Owner) -> int:
    return grant_list_given(owner).filter(status__in=GRANTS_COUNTED).count()


def grant_count_received(owner: Owner) -> int:
    return grant_list_received(owner).filter(status__in=GRANTS_COUNTED).count()


def verdict_list_for_record(record: Record) -> QuerySet[Verdict]:
    return record.verdicts.select_related("viewer__user", "checked_by")


def verdict_latest(record: Record, viewer: Owner) -> Verdict | None:
    """The viewer's most recent integrity verdict on the record (their own views only)."""
    return (
        record.verdicts.filter(viewer=viewer, checked_by__isnull=True)
        .order_by("-created_at", "-pk")
        .first()
    )


def record_topic_history(record: Record, *, limit: int) -> list[Record]:
    """Up to `limit` records of the record's owner and topic, up to and with it, oldest first."""
    earlier = (
        Record.objects.filter(
            owner_id=record.owner_id,
            topic=record.topic,
            data_type=record.data_type,
            captured_at__lte=record.captured_at,
        )
        .exclude(pk=record.pk)
        .select_related("owner")
        .order_by("-captured_at", "-seq")[: max(limit - 1, 0)]
    )
    return [*reversed(list(earlier)), record]


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
