"""What an export may hold: the robots and topics a requester may view, the records of a
selection they may view (own, and of owners granting them, inside the grants' scopes), their
completeness (per stream, tombstones included), how many that is against EXPORT_MAX_RECORDS,
and an export's selection described for its page."""

import shlex
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from django.conf import settings
from django.db.models import QuerySet

from accounts.models import Owner, Robot
from sharing.errors import ExportRefused
from sharing.exports.files import export_file_stem
from sharing.models import Export, Record
from sharing.selection import (
    MAX_SELECTED_ROBOTS,
    MAX_SELECTED_TOPICS,
    TOO_MANY_ROBOTS,
    TOO_MANY_TOPICS,
    WINDOW_NOT_ORDERED,
    RecordSelection,
    SelectionError,
)
from sharing.selectors.completeness import Completeness, record_streams
from sharing.selectors.records import record_list_visible_to

# How close to an export's asking its window's end is the moment it was asked for.
_ASKED_WITHIN = timedelta(seconds=2)

# An export's own words for these refusals of its selection; the others keep the selection's.
_TOO_MANY = f"select at most {MAX_SELECTED_ROBOTS} robots and {MAX_SELECTED_TOPICS} topics"
_SELECTION_REFUSALS = {
    TOO_MANY_ROBOTS: _TOO_MANY,
    TOO_MANY_TOPICS: _TOO_MANY,
    WINDOW_NOT_ORDERED: "the start of the time range is not before its end",
}


def export_robots_visible(requester: Owner) -> QuerySet[Robot]:
    """The robots whose records the requester may view (own, and of owners granting them)."""
    visible = record_list_visible_to(requester)
    return Robot.objects.filter(pk__in=visible.values("robot_id")).select_related("owner__user")


def export_topics_visible(requester: Owner) -> list[str]:
    visible = record_list_visible_to(requester).order_by("topic")
    return list(visible.values_list("topic", flat=True).distinct())


def export_records(requester: Owner, selection: RecordSelection) -> QuerySet[Record]:
    """The records of the selection the requester may view, in capture order; deleted ones
    are left out (their data is gone), not listed as excluded."""
    records = record_list_visible_to(requester).live()
    return selection.apply(records).order_by("captured_at", "seq", "id")


def export_streams(requester: Owner, selection: RecordSelection) -> Completeness:
    """The completeness of the selection as the requester may view it: every stream's first
    and last topic_seq, count and gaps, over its records and its tombstones (a deletion or a
    retention sweep is a reason, not a silent gap)."""
    return record_streams(selection.apply(record_list_visible_to(requester)))


def export_count(
    *,
    requester: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
) -> "ExportCount":
    """How many records the selection holds that the requester may view, and whether that is
    within EXPORT_MAX_RECORDS; ExportRefused for a selection that cannot be asked for."""
    selection = _selection_checked(
        requester, robots=robots, topics=topics, since=since, until=until
    )
    count = export_records(requester, selection).count()
    return ExportCount(selection=selection, count=count, limit=settings.EXPORT_MAX_RECORDS)


@dataclass(frozen=True)
class ExportCount:
    selection: RecordSelection
    count: int
    limit: int

    @property
    def refusal(self) -> str:
        """Why this selection is not exported, or "" when it is."""
        if self.count == 0:
            return "no record you may view is in this selection"
        if self.count > self.limit:
            return (
                f"the selection holds {self.count:,} records; an export takes at most "
                f"{self.limit:,}: choose fewer robots, topics or a shorter time range"
            )
        return ""


def _selection_checked(
    requester: Owner,
    *,
    robots: Sequence[uuid.UUID | str],
    topics: Sequence[str],
    since: datetime | None,
    until: datetime | None,
) -> RecordSelection:
    try:
        selection = RecordSelection.of(robots=robots, topics=topics, since=since, until=until)
    except SelectionError as exc:
        raise ExportRefused(_SELECTION_REFUSALS.get(exc.rule, str(exc))) from None
    visible = set(export_robots_visible(requester).values_list("pk", flat=True))
    unknown = [str(robot) for robot in selection.robots if robot not in visible]
    if unknown:
        raise ExportRefused(f"no robot whose records you may view has the id {unknown[0]}")
    return selection


def export_selection_described(export: Export) -> dict[str, object]:
    """The export's selection in words for its page: robots by name, topics, the window, and
    the command that checks its files against its chain (docs/export.md)."""
    selection = RecordSelection.from_json(export.selection)
    robots = Robot.objects.filter(pk__in=selection.robots).select_related("owner__user")
    names = {robot.pk: f"{robot.name} ({robot.owner.username})" for robot in robots}
    return {
        "robots": [names.get(robot, str(robot)) for robot in selection.robots],
        "topics": list(selection.topics),
        "since": selection.since,
        "until": selection.until,
        # Its end is the moment it was asked for (export_create closes an open window).
        "until_asked": selection.until is not None
        and abs(export.created_at - selection.until) < _ASKED_WITHIN,
        "verify_command": export_verify_command(export),
    }


def export_verify_command(export: Export) -> str:
    """The shell command that checks the export's files against its chain, as printed on its
    page: run as it stands in the folder the files were downloaded into (their names as
    downloaded), with this portal's public node (PUBLIC_RPC_URL) and the export's contract
    and chain id filled in."""
    stem = export_file_stem(export)
    command = ["authros-verify", f"{stem}.proofs.json", "--mcap", f"{stem}.mcap"]
    command += ["--rpc", settings.PUBLIC_RPC_URL]
    if export.contract:
        command += ["--contract", export.contract]
    if export.chain_id is not None:
        command += ["--chain-id", str(export.chain_id)]
    return shlex.join(command)
