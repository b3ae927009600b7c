"""Reads of exports: an owner's exports (only their requester sees one), and those
unfinished, by status (the metrics)."""

import uuid

from django.db.models import Count, QuerySet

from accounts.models import Owner
from sharing.models import Export


def export_list_of(owner: Owner) -> QuerySet[Export]:
    """The owner's exports, newest first (only their requester sees an export)."""
    return Export.objects.filter(requester=owner).order_by("-created_at")


def export_of(owner: Owner, export_id: uuid.UUID | str) -> Export | None:
    try:
        wanted = uuid.UUID(str(export_id))
    except ValueError:
        return None
    return export_list_of(owner).filter(pk=wanted).first()


def export_counts_unfinished() -> dict[str, int]:
    """Exports queued and running, by status (the metrics)."""
    unfinished = [Export.Status.QUEUED, Export.Status.RUNNING]
    counts = dict.fromkeys(unfinished, 0)
    rows = (
        Export.objects.filter(status__in=unfinished).values_list("status").annotate(n=Count("id"))
    )
    counts.update(dict(rows))
    return {str(status): count for status, count in counts.items()}
