"""The access log's lines for a read: one `Access` per record owner whose records the read took
(a record page, a gallery page, a plot, an export, an operator's check), opened before or with
its records' verdicts, and the rule that keeps refused views from filling an owner's log.

`accesses_open` sums the records up per owner; `accesses_open_for` takes sums already made (an
export counts its records in the database). `access_refused_again` is the coalescing of refused
views (docs/security.md): a read refused whole, by a viewer whose last own read of the same
owner's records was refused within REFUSED_VIEWS_COALESCED, is answered as that one was and
not written again. A plot's refresh (its newer records only) adds its records to the viewer's
line of the same plot begun within PLOT_REFRESHES_COALESCED: a page plotting every 5 s is one
line per window, its verdicts (one per record and check) all under it.
"""

import uuid
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from datetime import timedelta
from typing import Any

from django.db.models import F
from django.utils import timezone

from accounts.models import Owner
from sharing.models import Access, Credential, Record, Verdict

# Refused views of one owner's records by one viewer in a row leave one verdict and access line
# per this long: the first; later ones are answered the same and not written, so an owner
# without a grant cannot fill another owner's access log (docs/security.md). A view that passed
# in between starts a new line.
REFUSED_VIEWS_COALESCED = timedelta(hours=1)
# A plot's refreshes add to the line its viewer began this recently (same robot, topic and
# credential); later, a refresh begins a new line.
PLOT_REFRESHES_COALESCED = timedelta(minutes=10)


@dataclass(frozen=True)
class OwnerRead:
    """What one read takes of one owner's records: how many, the record when it is one, the
    robot and the topic when they all share them (an export counts them in the database)."""

    owner_id: int
    count: int
    record: Record | None
    robot_id: uuid.UUID | None
    topic: str | None


def credential_check(credential: str, token_id: int | None) -> None:
    """An access's credential is one of Credential, with a token exactly for `token`."""
    if credential not in Credential.values:
        raise ValueError(f"unknown credential {credential!r}")
    if (credential == Credential.TOKEN) != (token_id is not None):
        raise ValueError("a token id goes with the `token` credential, and only with it")


def access_kind_check(kind: str) -> None:
    if kind not in Access.Kind.values:
        raise ValueError(f"unknown access kind {kind!r}")


def accesses_open(
    *,
    kind: str,
    viewer_id: int,
    records: Sequence[Record],
    credential: str,
    token_id: int | None,
    checked_by_id: int | None = None,
) -> dict[int, int]:
    """The access log's line for a read of these records: one Access per record owner (so that
    each owner's log is one range), naming how many of the owner's records it read, the record
    when it is one, the robot and topic when they all share them. Record owner id -> Access id."""
    by_owner: dict[int, list[Record]] = defaultdict(list)
    for record in records:
        by_owner[record.owner_id].append(record)
    reads = [
        OwnerRead(
            owner_id=owner_id,
            count=len(owned),
            record=owned[0] if len(owned) == 1 else None,
            robot_id=_shared({record.robot_id for record in owned}),
            topic=_shared({record.topic for record in owned}),
        )
        for owner_id, owned in by_owner.items()
    ]
    return accesses_open_for(
        kind=kind,
        viewer_id=viewer_id,
        reads=reads,
        credential=credential,
        token_id=token_id,
        checked_by_id=checked_by_id,
    )


def accesses_open_for(
    *,
    kind: str,
    viewer_id: int,
    reads: Sequence[OwnerRead],
    credential: str,
    token_id: int | None,
    checked_by_id: int | None = None,
    refresh: bool = False,
) -> dict[int, int]:
    """accesses_open for reads already summed up per owner. Record owner id -> Access id."""
    named = _names(kind, viewer_id, reads, credential, token_id, checked_by_id)
    lines: dict[int, int] = {}
    if refresh and kind == Access.Kind.PLOT and checked_by_id is None:
        lines = _lines_recent(named)
    for read in reads:
        if read.owner_id in lines:
            added = F("count") + read.count
            Access.objects.filter(pk=lines[read.owner_id]).update(count=added, record=None)
    rows = [
        Access(**named[read.owner_id], count=read.count, record=read.record)
        for read in reads
        if read.owner_id not in lines
    ]
    return lines | {row.record_owner_id: row.pk for row in Access.objects.bulk_create(rows)}


def reads_new_to_lines(
    *,
    viewer_id: int,
    reads: Sequence[OwnerRead],
    record_ids: Sequence[str],
    credential: str,
    token_id: int | None,
) -> list[OwnerRead]:
    """A plot refresh's reads, each owner's count without the records that the line it adds to
    holds already: a record read again (not anchored at the last refresh, checked now) is one
    record of the line, not two; its new verdict goes under the line all the same."""
    named = _names(Access.Kind.PLOT, viewer_id, reads, credential, token_id, None)
    lines = _lines_recent(named)
    if not lines:
        return list(reads)
    held = Counter(
        access_id
        for access_id, _ in Verdict.objects.filter(
            access_id__in=lines.values(), record_id__in=record_ids
        )
        .order_by()  # Verdict's default ordering would join the DISTINCT
        .values_list("access_id", "record_id")
        .distinct()
    )
    return [
        replace(read, count=max(read.count - held[lines[read.owner_id]], 0))
        if read.owner_id in lines
        else read
        for read in reads
    ]


def _names(
    kind: str,
    viewer_id: int,
    reads: Sequence[OwnerRead],
    credential: str,
    token_id: int | None,
    checked_by_id: int | None,
) -> dict[int, dict[str, Any]]:
    """Per record owner, what names a read's line: its kind, viewer, credential, robot, topic."""
    return {
        read.owner_id: {
            "kind": kind,
            "viewer_id": viewer_id,
            "record_owner_id": read.owner_id,
            "checked_by_id": checked_by_id,
            "credential": credential,
            "token_id": token_id,
            "robot_id": read.robot_id,
            "topic": read.topic or "",
        }
        for read in reads
    }


def accesses_withdraw(
    accesses: dict[int, int], reads: Sequence[OwnerRead], *, refresh: bool = False
) -> None:
    """A read that no check answered is no access: its lines without verdicts removed, and a
    refresh's records (`reads`, per owner) taken off the earlier line it added them to."""
    Access.objects.filter(pk__in=accesses.values(), verdicts__isnull=True).delete()
    if refresh:
        counts = {read.owner_id: read.count for read in reads}
        for owner_id, access_id in accesses.items():
            Access.objects.filter(pk=access_id).update(count=F("count") - counts.get(owner_id, 0))


def _lines_recent(named: dict[int, dict[str, Any]]) -> dict[int, int]:
    """Per record owner, the latest line named the same (the viewer's own, of the same kind,
    robot, topic and credential) begun within PLOT_REFRESHES_COALESCED."""
    begun = timezone.now() - PLOT_REFRESHES_COALESCED
    lines: dict[int, int] = {}
    for owner_id, names in named.items():
        line = (
            Access.objects.filter(**names, created_at__gte=begun)
            .order_by("-created_at", "-id")
            .values_list("pk", flat=True)
            .first()
        )
        if line is not None:
            lines[owner_id] = line
    return lines


# The reads a person asks for at a page or the API; an export and an operator's check are
# always written.
_COALESCED_KINDS = (Access.Kind.VIEW, Access.Kind.PAGE, Access.Kind.PLOT)


def access_refused_again(
    records: Sequence[Record],
    outcomes: Sequence[str],
    viewer: Owner,
    *,
    kind: str,
    accesses: dict[int, int] | None,
) -> Verdict | None:
    """For a viewer's own read (of `kind`) refused whole, of one owner's records: the viewer's
    last own verdict on a record of that owner, if it was refused within
    REFUSED_VIEWS_COALESCED; None when the read is to be written. A read whose line is open
    already (`accesses`, opened by the web) is coalesced only when that line is this batch's
    alone, and the line is then removed: it has no verdicts yet, and the refused read is
    answered as the one before it."""
    owners = {record.owner_id for record in records}
    if kind not in _COALESCED_KINDS or len(owners) != 1:
        return None
    if any(outcome != Verdict.Outcome.NO_ACCESS for outcome in outcomes):
        return None
    (owner_id,) = owners
    last = (
        Verdict.objects.filter(
            access__viewer=viewer,
            access__record_owner_id=owner_id,
            access__checked_by__isnull=True,
            created_at__gte=timezone.now() - REFUSED_VIEWS_COALESCED,
        )
        .order_by("-created_at", "-pk")
        .first()
    )
    if last is None or last.outcome != Verdict.Outcome.NO_ACCESS:
        return None
    if accesses is not None:
        opened = Access.objects.filter(pk=accesses.get(owner_id), count=len(records))
        if not opened.delete()[0]:  # the line is a bigger read's: it is written
            return None
    return last


def _shared(values: set[Any]) -> Any:
    return next(iter(values)) if len(values) == 1 else None
