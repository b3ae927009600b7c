"""Asking for an export: the selection checked, the Export row written and `export_run`
queued on commit (sharing.tasks.export_run); an export made again of an earlier one's
selection, under the requester's access now."""

import uuid
from collections.abc import Sequence
from datetime import datetime, timedelta

from django.conf import settings
from django.db import transaction
from django.utils import timezone

from accounts.models import Owner, OwnerToken
from core.outbox import enqueue
from sharing.errors import ExportNotFound, ExportRefused
from sharing.exports.selection import export_count
from sharing.models import Credential, Export
from sharing.selection import RecordSelection
from sharing.selectors.exports import export_of

EXPORT_TASK = "sharing.tasks.export_run"


def export_create(
    *,
    requester: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
    credential: str = Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> Export:
    """Check the selection (robots and topics, empty: all; capture times [since, until)) and
    queue its export; ExportRefused if it cannot be exported (its count says why). The
    credential (and token) that asked is what its access-log lines record.

    A window open at its end is closed at the moment asked, rounded up to the second (a record
    captured earlier in that second is in it): the export holds the records of its selection as
    of then, not what robots capture while it runs, so its count is the one it was asked with
    and its progress never passes 100% (issue 48)."""
    now = timezone.now()
    asked = now.replace(microsecond=0) + (timedelta(seconds=1) if now.microsecond else timedelta())
    if until is None and (since is None or since < asked):
        until = asked
    counted = export_count(
        requester=requester, robots=robots, topics=topics, since=since, until=until
    )
    if counted.refusal:
        raise ExportRefused(counted.refusal)
    with transaction.atomic():
        export = Export.objects.create(
            requester=requester,
            credential=credential,
            token=token,
            selection=counted.selection.as_json(),
            total=counted.count,
            expires_at=timezone.now() + timedelta(hours=settings.EXPORT_TTL_HOURS),
        )
        transaction.on_commit(lambda: enqueue(EXPORT_TASK, str(export.pk)))
    return export


def export_rebuild(
    *,
    requester: Owner,
    export_id: uuid.UUID | str,
    credential: str = Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> Export:
    """A new export of an export's selection, made under the requester's access now, asked
    for by `credential`."""
    export = export_of(requester, export_id)
    if export is None:
        raise ExportNotFound("no such export of yours")
    selection = RecordSelection.from_json(export.selection)
    return export_create(
        requester=requester,
        robots=selection.robots,
        topics=selection.topics,
        since=selection.since,
        until=selection.until,
        credential=credential,
        token=token,
    )
