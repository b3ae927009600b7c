"""Every record counted (DESIGN.md "Provenance v2"): per stream (signer, topic), the first and
last `topic_seq` of the records in a reader's window, how many are there, and every gap with
the portal's reason for it.

A stream's numbers run 0, 1, 2, ... with none skipped (the robot signs them), so every number
between a window's first and last that no live record holds is a gap: `deleted` (a tombstone
of the owner's deletion, with when) or `retention` (a tombstone of the robot's retention
policy, with when), else `missing`: the portal has nothing for it, which no owner's action
explains. The answer is the portal's own reading of its rows; a reader who holds the window's
records checks it from their signed headers (authros-verify --complete).

    streams = record_streams(records)   # records: a reader's scope and window, tombstones in
"""

import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from itertools import groupby

from django.db.models import Count, F, Max, Min, Q, QuerySet, Window
from django.db.models.functions import Lag

from accounts.models import Owner
from sharing.models import Record
from sharing.selection import RecordSelection
from sharing.selectors.records import record_list_visible_to

GAP_MISSING = "missing"
GAP_DELETED = "deleted"
GAP_RETENTION = "retention"
GAP_REASONS = (GAP_MISSING, GAP_DELETED, GAP_RETENTION)
_REASON_OF_DELETION = {
    Record.Deletion.OWNER: GAP_DELETED,
    Record.Deletion.ACCOUNT: GAP_DELETED,
    Record.Deletion.RETENTION: GAP_RETENTION,
}


@dataclass(frozen=True)
class Gap:
    """The numbers `start`..`end` (both in) of a stream that no live record holds."""

    start: int
    end: int
    reason: str  # one of GAP_REASONS
    at: datetime | None = None  # when they were deleted (the latest of the run), if they were

    @property
    def size(self) -> int:
        return self.end - self.start + 1

    def as_json(self) -> dict[str, object]:
        answer: dict[str, object] = {"from": self.start, "to": self.end, "reason": self.reason}
        if self.at is not None:
            answer["at"] = self.at.isoformat()
        return answer


@dataclass(frozen=True)
class Stream:
    """One signer's records of one topic in a window: `count` live ones, from `first` to `last`
    (tombstones included), and the gaps between."""

    signer: str
    topic: str
    robot_id: str
    first: int
    last: int
    count: int
    gaps: tuple[Gap, ...] = field(default=())

    @property
    def missing(self) -> int:
        """How many numbers are gone without a reason the portal can give."""
        return sum(gap.size for gap in self.gaps if gap.reason == GAP_MISSING)

    @property
    def complete(self) -> bool:
        return not self.gaps

    def as_json(self) -> dict[str, object]:
        return {
            "signer": self.signer,
            "topic": self.topic,
            "robot": self.robot_id,
            "first": self.first,
            "last": self.last,
            "count": self.count,
            "gaps": [gap.as_json() for gap in self.gaps],
        }


@dataclass(frozen=True)
class Completeness:
    """The streams of a window, and how many of its records no signer counts (v1 or
    unsigned records, which carry no topic_seq)."""

    streams: tuple[Stream, ...]
    uncounted: int

    @property
    def missing(self) -> int:
        return sum(stream.missing for stream in self.streams)

    @property
    def gaps(self) -> int:
        return sum(len(stream.gaps) for stream in self.streams)

    @property
    def counted(self) -> int:
        return sum(stream.count for stream in self.streams)

    def as_json(self) -> dict[str, object]:
        return {
            "streams": [stream.as_json() for stream in self.streams],
            "uncounted": self.uncounted,
        }


def record_streams(records: QuerySet[Record]) -> Completeness:
    """The completeness of `records` (a reader's scope and window, tombstones included: a
    deletion is a reason, not a gap).

    At most four queries, whatever the window holds: each stream's first, last and counts
    (one aggregate); then, only when some stream has fewer rows than numbers, the rows that
    follow a skipped number (LAG over the stream index); only when some stream has tombstones,
    the tombstones in order, joined into runs; and the count of the uncounted. A complete
    window of any size is the aggregate and the count; the rows read in Python are the
    tombstones and the skips, never the live records.
    """
    counted = records.filter(topic_seq__isnull=False).order_by()
    spans = _spans(counted)
    skipped = any(span.rows < span.last - span.first + 1 for span in spans.values())
    deleted = any(span.live < span.rows for span in spans.values())
    gaps: dict[tuple[str, str], list[Gap]] = {key: [] for key in spans}
    if skipped:
        for signer, topic, before, after in _skips(counted):
            gaps[signer, topic].append(Gap(before + 1, after - 1, GAP_MISSING))
    if deleted:
        for (signer, topic), runs in _tombstone_runs(counted):
            gaps[signer, topic].extend(runs)
    streams = tuple(
        Stream(
            signer=signer,
            topic=topic,
            robot_id=span.robot_id,
            first=span.first,
            last=span.last,
            count=span.live,
            gaps=_gaps_joined(gaps[signer, topic]),
        )
        for (signer, topic), span in sorted(spans.items())
    )
    uncounted = records.filter(topic_seq__isnull=True, deleted_at__isnull=True).count()
    return Completeness(streams, uncounted)


@dataclass
class _Span:
    robot_id: str
    first: int
    last: int
    rows: int  # tombstones included
    live: int


def _spans(counted: QuerySet[Record]) -> dict[tuple[str, str], _Span]:
    """(signer, topic) -> its numbers' span and counts in the window: one GROUP BY. The robot
    is grouped by too (a key is one robot's, but the database does not know it): a key found
    under two robots is one stream, named by the first."""
    rows = counted.values("signer", "topic", "robot_id").annotate(
        first=Min("topic_seq"),
        last=Max("topic_seq"),
        rows=Count("topic_seq"),
        live=Count("topic_seq", filter=Q(deleted_at__isnull=True)),
    )
    spans: dict[tuple[str, str], _Span] = {}
    for row in rows:
        key = (row["signer"], row["topic"])
        span = spans.get(key)
        if span is None:
            spans[key] = _Span(
                str(row["robot_id"]), row["first"], row["last"], row["rows"], row["live"]
            )
        else:
            span.first, span.last = min(span.first, row["first"]), max(span.last, row["last"])
            span.rows += row["rows"]
            span.live += row["live"]
    return spans


def _skips(counted: QuerySet[Record]) -> Iterator[tuple[str, str, int, int]]:
    """(signer, topic, before, after) for each pair of numbers of a stream held by rows, with
    none between them held: the numbers before+1..after-1 are missing."""
    return (
        counted.annotate(
            before=Window(
                Lag("topic_seq"),
                partition_by=[F("signer"), F("topic")],
                order_by=F("topic_seq").asc(),
            )
        )
        .filter(before__lt=F("topic_seq") - 1)
        .values_list("signer", "topic", "before", "topic_seq")
        .iterator(chunk_size=2000)
    )


def _tombstone_runs(counted: QuerySet[Record]) -> Iterator[tuple[tuple[str, str], list[Gap]]]:
    """Per stream, its tombstones as runs of consecutive numbers deleted for one reason, each
    with the latest deletion of the run."""
    rows = (
        counted.filter(deleted_at__isnull=False)
        .order_by("signer", "topic", "topic_seq")
        .values_list("signer", "topic", "topic_seq", "deleted_at", "deletion_reason")
        .iterator(chunk_size=5000)
    )
    for key, stream_rows in groupby(rows, key=lambda row: (row[0], row[1])):
        runs: list[Gap] = []
        for _signer, _topic, topic_seq, deleted_at, reason in stream_rows:
            gap_reason = _REASON_OF_DELETION.get(reason, GAP_DELETED)
            _gap_add(runs, Gap(topic_seq, topic_seq, gap_reason, deleted_at))
        yield key, runs


def _gaps_joined(gaps: list[Gap]) -> tuple[Gap, ...]:
    """The gaps of a stream in order, those that touch with one reason joined."""
    joined: list[Gap] = []
    for gap in sorted(gaps, key=lambda gap: gap.start):
        _gap_add(joined, gap)
    return tuple(joined)


def _gap_add(gaps: list[Gap], gap: Gap) -> None:
    """Append `gap`, joined to the one before when they touch and share their reason."""
    if gaps and gaps[-1].end + 1 == gap.start and gaps[-1].reason == gap.reason:
        before = gaps[-1]
        at = max((moment for moment in (before.at, gap.at) if moment is not None), default=None)
        gaps[-1] = Gap(before.start, gap.end, gap.reason, at)
    else:
        gaps.append(gap)


def completeness_visible_to(
    viewer: Owner,
    *,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> Completeness:
    """The completeness of the window [since, until) of captures that `viewer` may see (their
    own records and, of a live grant, those in its scope: record_list_visible_to, tombstones
    included), of one robot and one topic if given. A robot or topic outside the viewer's
    scope answers as one that does not exist: no stream."""
    window = RecordSelection.from_filters(robot=robot, topic=topic, since=since, until=until)
    return record_streams(window.apply(record_list_visible_to(viewer)))


def record_list_window(
    records: QuerySet[Record],
    *,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    data_type: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
    owner: str | None = None,
    **_others: object,
) -> QuerySet[Record]:
    """The window of a record list's filters, tombstones included and whatever the status
    filter (a page's anchoring status is no gap): what the list's completeness is read from.
    Other filters (`status`) are not part of a window."""
    window = RecordSelection.from_filters(robot=robot, topic=topic, since=since, until=until).apply(
        records
    )
    if data_type:
        window = window.filter(data_type=data_type)
    if owner:
        window = window.filter(owner__user__username=owner)
    return window


def gap_around(
    records: QuerySet[Record], stream: Stream, gap: Gap
) -> tuple[datetime | None, datetime | None]:
    """The capture times that bound `gap` in `records` (the window it was found in), for a
    link to the list that shows it: of a missing gap the records on either side (there are
    rows there, live or tombstones: that is how the gap was found); of a deletion its first
    and last tombstone. None for an end not found (records that are not the gap's window)."""
    ends = (gap.start - 1, gap.end + 1) if gap.reason == GAP_MISSING else (gap.start, gap.end)
    around = dict(
        records.filter(signer=stream.signer, topic=stream.topic, topic_seq__in=ends)
        .order_by()
        .values_list("topic_seq", "captured_at")
    )
    return around.get(ends[0]), around.get(ends[1])
