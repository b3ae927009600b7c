"""What the record list and the robot page say of their window's completeness: "n records,
nothing missing", or each gap named with its reason (and when, for a deletion), with a link
to the records around it (sharing/templates: sharing/_completeness.html).

A page counts at most COMPLETENESS_PAGE_MAX records (the API counts any window): a longer
window says so and asks for a shorter one, so that no page waits on a count of millions. A
missing gap found here is told to the robot's owner (sharing/services/completeness.py)."""

from dataclasses import dataclass
from datetime import datetime, timedelta
from urllib.parse import urlencode

from django.db.models import QuerySet

from accounts.models import Robot
from sharing.models import Record
from sharing.selectors.completeness import (
    GAP_MISSING,
    Completeness,
    Gap,
    Stream,
    gap_around,
    record_streams,
)
from sharing.selectors.records import RECORD_STATUS_DELETED
from sharing.services.completeness import records_missing_alerts_raise

# Records of a window a page counts at most (about 0.2 s on SQLite, measured on this machine
# with 100,000 records: 0.1 s the spans, 0.2 s the skipped numbers of a stream with a gap).
COMPLETENESS_PAGE_MAX = 50_000
# Gaps a page names, with their links; the API answers all of them.
GAPS_SHOWN = 20
# A window's gaps listed openly up to this many; more are in a details element.
GAPS_OPEN = 5
_FILTER_TIME = "%Y-%m-%d %H:%M:%S"


@dataclass(frozen=True)
class GapShown:
    stream: Stream
    gap: Gap
    robot_name: str
    link: str  # the record list around the gap

    @property
    def missing(self) -> bool:
        return self.gap.reason == GAP_MISSING


@dataclass(frozen=True)
class CompletenessShown:
    """A window's completeness as a page shows it; `completeness` None when the window holds
    more than COMPLETENESS_PAGE_MAX records (`records` of them)."""

    completeness: Completeness | None
    records: int = 0
    gaps: tuple[GapShown, ...] = ()

    @property
    def too_many(self) -> bool:
        return self.completeness is None

    @property
    def more_gaps(self) -> int:
        return 0 if self.completeness is None else self.completeness.gaps - len(self.gaps)

    @property
    def missing_gaps(self) -> tuple[GapShown, ...]:
        return tuple(shown for shown in self.gaps if shown.missing)

    @property
    def listed_openly(self) -> bool:
        return len(self.gaps) <= GAPS_OPEN

    @property
    def page_max(self) -> int:
        return COMPLETENESS_PAGE_MAX


def completeness_shown(window: QuerySet[Record], *, list_url: str) -> CompletenessShown:
    """The completeness of `window` (a page's records: the reader's scope and filters,
    tombstones included), its first GAPS_SHOWN gaps with links into `list_url` (the record
    list they are in); its missing gaps told to their owners."""
    records = window.order_by().count()
    if records > COMPLETENESS_PAGE_MAX:
        return CompletenessShown(None, records)
    completeness = record_streams(window)
    records_missing_alerts_raise(completeness)
    found = [(stream, gap) for stream in completeness.streams for gap in stream.gaps]
    found = found[:GAPS_SHOWN]
    robots = Robot.objects.filter(pk__in={stream.robot_id for stream, _ in found})
    names = {str(pk): name for pk, name in robots.values_list("pk", "name")}
    gaps = tuple(
        GapShown(
            stream=stream,
            gap=gap,
            robot_name=names.get(stream.robot_id, ""),
            link=_link(window, list_url, stream, gap),
        )
        for stream, gap in found
    )
    return CompletenessShown(completeness, records, gaps)


def _link(window: QuerySet[Record], list_url: str, stream: Stream, gap: Gap) -> str:
    """The list of the stream's records from the one before a missing gap to the one after it,
    or of a deletion's tombstones (with the status filter "deleted"), times to the second (a
    robot's clock may run back: the earlier of the two first)."""
    ends = [moment for moment in gap_around(window, stream, gap) if moment is not None]
    query: dict[str, str] = {"robot": stream.robot_id, "topic": stream.topic}
    if ends:
        query["since"] = _second(min(ends)).strftime(_FILTER_TIME)
        query["until"] = (_second(max(ends)) + timedelta(seconds=1)).strftime(_FILTER_TIME)
    if gap.reason != GAP_MISSING:
        query["status"] = RECORD_STATUS_DELETED
    return f"{list_url}?{urlencode(query)}"


def _second(moment: datetime) -> datetime:
    return moment.replace(microsecond=0)
