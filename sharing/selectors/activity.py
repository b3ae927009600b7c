"""Reads of what happened and what waits: an owner's transactions as the worker indexed
them (the audit page, sharing/audit.py) and the alarms about their records, and the chain work
waiting in the database (the operator's status, the metrics)."""

from datetime import datetime

from django.db.models import F, Q, QuerySet, Window
from django.db.models.functions import RowNumber

from accounts.models import ChainActivity, Owner
from sharing.models import Grant, Record, SecurityEvent


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


def record_oldest_pending_since() -> datetime | None:
    """When the oldest record still waiting for anchoring was stored (the metrics' backlog
    age); one row of the (status, created_at) index."""
    return (
        Record.objects.filter(status=Record.Status.PENDING)
        .order_by("created_at")
        .values_list("created_at", flat=True)
        .first()
    )
