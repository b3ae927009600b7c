"""What the portal does when a stored envelope fails its check against the chain: the record is
marked tampered, a SecurityEvent and the owner's alert are written, the security log says so,
and the cached copy is dropped so that the next view reads durable storage again."""

import logging

from django.utils import timezone

from accounts.models import Owner
from alerts.services import record_tampered_alert
from sharing.cache import envelope_cache_evict
from sharing.models import Record, SecurityEvent

security_log = logging.getLogger("authros.security")


def record_tampered_respond(
    *, record: Record, viewer: Owner, source: str, computed: str, chain: str
) -> None:
    """Answer a failed check of `record` seen by `viewer` on its `source` copy ("cache" or
    "storage"): `computed` is the stored copy's SM3 (or "missing"), `chain` the anchored one."""
    Record.objects.filter(pk=record.pk).update(tampered_at=timezone.now())
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.TAMPERED_ON_VIEW,
        record=record,
        owner=record.owner,
        detail={"viewer": viewer.username, "source": source, "computed": computed, "chain": chain},
    )
    record_tampered_alert(
        owner=record.owner,
        record_id=record.pk,
        topic=record.topic,
        robot=record.robot.name,
        source=source,
    )
    security_log.error(
        "record %s failed its integrity check (%s copy): computed %s, chain %s",
        record.pk,
        source,
        computed,
        chain,
    )
    # The next view reads durable storage again instead of the bad cached copy.
    envelope_cache_evict(record.pk)
