"""Reads: which records and grants an owner may see."""

import uuid
from datetime import datetime

from django.db.models import Q, QuerySet

from accounts.models import Owner
from chainworker.chain import ChainEvent
from chainworker.selectors import deployment_active
from chainworker.services import chain_client
from sharing.models import Grant, Record, Verdict

# Contract events about an owner, and the argument that names the owner in each.
OWNER_EVENT_ARGS = {
    "Enrolled": ("eoa",),
    "Registered": ("eoa",),
    "KeyRotated": ("eoa",),
    "DataUploaded": ("owner",),
    "AuthorityGranted": ("owner", "grantee"),
    "AuthorityRevoked": ("owner", "grantee"),
}


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
    return Grant.objects.filter(owner=owner).select_related("grantee__user")


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
        .order_by("-captured_at", "-seq")[: max(limit - 1, 0)]
    )
    return [*reversed(list(earlier)), record]


def owners_by_address(addresses: list[str]) -> dict[str, Owner]:
    """Owners by lower-case EOA address."""
    lowered = {address.lower() for address in addresses}
    owners = Owner.objects.select_related("user").filter(
        Q(eoa_address__in=addresses) | Q(eoa_address__in=lowered)
    )
    return {owner.eoa_address.lower(): owner for owner in owners}


def chain_events_of_owner(owner: Owner) -> list[ChainEvent]:
    """The owner's history read from the contract's logs, oldest first.

    Enrolment, registration, key rotations, uploads, and grants given and received.
    Raises chainworker.chain.ChainError when the node is down or nothing is deployed.
    """
    client = chain_client()
    deployment = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
    from_block = deployment.block_number if deployment else 0
    return client.events_naming(owner.eoa_address, OWNER_EVENT_ARGS, from_block)


def chain_backlog() -> dict[str, int]:
    """Records and grants waiting for the chain, and records whose anchoring failed."""
    return {
        "records": Record.objects.filter(status=Record.Status.PENDING).count(),
        "failed_records": Record.objects.filter(status=Record.Status.FAILED).count(),
        "grants": Grant.objects.filter(
            status__in=[Grant.Status.PENDING, Grant.Status.REVOKING]
        ).count(),
    }
