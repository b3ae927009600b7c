"""Exports withdrawn and expired: an export is downloadable only while its requester may
still view every record in it (`ExportRecord` lists them); a revocation, a changed or expired
grant, a deleted record or a closed account withdraws it, removing its key and its files
(`export_access_lost`, checked at every download and look, and by `exports_recheck`). The
periodic sweep also queues again exports whose message was lost, and expires old ones."""

from datetime import timedelta

from django.conf import settings
from django.db.models import Q
from django.utils import timezone

from accounts.models import Owner
from core.outbox import enqueue
from sharing.exports.create import EXPORT_TASK
from sharing.exports.files import export_files_remove
from sharing.models import Export, ExportRecord, Grant, Record
from sharing.selection import iso_utc
from sharing.selectors.grants import grant_live
from sharing.selectors.records import record_list_visible_to


def exports_sweep() -> dict[str, int]:
    """The periodic job: queue again exports whose message was lost (queued for longer than
    EXPORT_REQUEUE_AFTER seconds: a broker that was down), expire old ones, and withdraw the
    ones whose requester may no longer view every record in them (a grant that expired)."""
    stale = timezone.now() - timedelta(seconds=settings.EXPORT_REQUEUE_AFTER)
    requeued = 0
    for export_id in Export.objects.filter(
        status=Export.Status.QUEUED, created_at__lt=stale, expires_at__gt=timezone.now()
    ).values_list("pk", flat=True):
        requeued += enqueue(EXPORT_TASK, str(export_id))
    expired = exports_expire()
    return {"requeued": requeued, "expired": expired, "withdrawn": exports_recheck()}


def exports_expire() -> int:
    """Remove the files of exports past their expiry; how many expired."""
    expired = Export.objects.filter(expires_at__lte=timezone.now()).exclude(
        status__in=[Export.Status.EXPIRED, Export.Status.WITHDRAWN]
    )
    count = 0
    for export in expired:
        export_files_remove(export, status=Export.Status.EXPIRED, reason=None)
        count += 1
    return count


def exports_recheck(*, owner_id: int | None = None) -> int:
    """Withdraw each ready export whose requester may no longer view every record in it: of
    `owner_id`'s records or asked for by them (after a revocation, a changed grant, a
    deletion, a closed account), or every ready export (the sweep). How many were withdrawn."""
    ready = Export.objects.filter(status=Export.Status.DONE).select_related("requester__user")
    if owner_id is not None:
        ready = ready.filter(
            Q(requester_id=owner_id)
            | Q(pk__in=ExportRecord.objects.filter(record__owner_id=owner_id).values("export_id"))
        )
    withdrawn = 0
    for export in ready:
        withdrawn += export_withdrawn_if_lost(export) is not None
    return withdrawn


def export_access_lost(export: Export) -> str:
    """Why the export's requester may no longer have it, or "" while they may view every
    record in it (record_list_visible_to: their own, and others' inside a live grant's scope)
    and none of them is deleted."""
    if export.requester.deleted_at is not None:
        return "your account is closed"
    if not export.key_wrapped:
        # Made before exports were sealed: plaintext at rest, which must not stay.
        return "it was stored before exports were sealed; export again"
    contents = ExportRecord.objects.filter(export=export)
    ids = contents.values("record_id")
    inside = record_list_visible_to(export.requester).live().filter(pk__in=ids)
    if inside.count() == contents.count():
        return ""
    if Record.objects.filter(pk__in=ids, deleted_at__isnull=False).exists():
        return "a record in it was deleted, and its data with it"
    others = Record.objects.filter(pk__in=ids).exclude(owner_id=export.requester_id)
    grants = {}
    for owner_id in others.order_by().values_list("owner_id", flat=True).distinct():
        grants[owner_id] = grant_live(owner_id=owner_id, viewer=export.requester)
        if grants[owner_id] is None:
            return _grant_ended(owner_id, export.requester)
    for owner_id, grant in grants.items():
        theirs = others.filter(owner_id=owner_id)
        if grant.scope.apply(theirs).count() != theirs.count():
            return f"{grant.owner.username} narrowed your grant: records in it are outside it now"
    return "you may no longer view every record in it"


def _grant_ended(owner_id: int, requester: Owner) -> str:
    last = (
        Grant.objects.filter(owner_id=owner_id, grantee=requester)
        .select_related("owner__user")
        .order_by("-created_at")
        .first()
    )
    if last is None:
        return "you no longer have access to records in it"
    name = last.owner.username
    if last.status in (Grant.Status.REVOKING, Grant.Status.REVOKED):
        return f"{name} revoked your access to their records"
    if last.expires_at is not None and last.expires_at <= timezone.now():
        return f"your grant from {name} expired at {iso_utc(last.expires_at)}"
    return f"your access to {name}'s records is not live"


def export_withdrawn_if_lost(export: Export) -> str | None:
    """None while the export may be downloaded; else withdraw it (files and key gone) and
    answer why."""
    reason = export_access_lost(export)
    if not reason:
        return None
    export_files_remove(export, status=Export.Status.WITHDRAWN, reason=f"withdrawn: {reason}")
    return reason
