"""The sweep of chain work: anchoring and grants that waited too long, queued again.

Run by the beat (task `sharing.tasks.chain_work_sweep`): a message lost or a worker dead
leaves records pending and grants pending or revoking; their tasks are idempotent, so queueing
them again is always safe.
"""

from datetime import timedelta

from django.conf import settings
from django.utils import timezone

from core.outbox import enqueue
from sharing.models import Grant, Record
from sharing.services.anchoring import anchor_schedule


def chain_work_sweep() -> dict[str, int]:
    """Queue again anchoring and grants pending for longer than ANCHOR_STALE_AFTER (a lost
    message, a dead worker); their tasks are idempotent."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    owners = set(
        Record.objects.filter(status=Record.Status.PENDING, created_at__lt=cutoff).values_list(
            "owner_id", flat=True
        )
    )
    for owner_id in owners:
        anchor_schedule(owner_id=owner_id)
    grants = list(
        Grant.objects.filter(
            status__in=[Grant.Status.PENDING, Grant.Status.REVOKING], updated_at__lt=cutoff
        ).values_list("pk", flat=True)
    )
    for grant_pk in grants:
        enqueue("sharing.tasks.grant_sync", grant_pk)
    return {"anchor_owners": len(owners), "grants": len(grants)}
