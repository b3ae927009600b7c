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

from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from itertools import groupby

from django.db.models import QuerySet

from sharing.models import Record

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


# (signer, topic, robot id, topic_seq, deleted at, deletion reason)
_Row = tuple[str, str, object, int, datetime | None, str]


def record_streams(records: QuerySet[Record]) -> Completeness:
    """The completeness of `records` (a reader's scope and window, tombstones included: a
    deletion is a reason, not a gap), read in one pass over the stream index."""
    counted = records.filter(topic_seq__isnull=False).order_by("signer", "topic", "topic_seq")
    rows: Iterator[_Row] = counted.values_list(
        "signer", "topic", "robot_id", "topic_seq", "deleted_at", "deletion_reason"
    ).iterator(chunk_size=5000)
    streams = tuple(
        _stream(signer, topic, list(stream_rows))
        for (signer, topic), stream_rows in groupby(rows, key=lambda row: (row[0], row[1]))
    )
    uncounted = records.filter(topic_seq__isnull=True, deleted_at__isnull=True).count()
    return Completeness(streams, uncounted)


def _stream(signer: str, topic: str, rows: list[_Row]) -> Stream:
    gaps: list[Gap] = []
    count = 0
    expected = rows[0][3]
    for _signer, _topic, _robot, topic_seq, deleted_at, reason in rows:
        if topic_seq > expected:
            _gap_add(gaps, Gap(expected, topic_seq - 1, GAP_MISSING))
        if deleted_at is None:
            count += 1
        else:
            _gap_add(
                gaps,
                Gap(topic_seq, topic_seq, _REASON_OF_DELETION.get(reason, GAP_DELETED), deleted_at),
            )
        expected = max(expected, topic_seq + 1)
    return Stream(
        signer=signer,
        topic=topic,
        robot_id=str(rows[0][2]),
        first=rows[0][3],
        last=rows[-1][3],
        count=count,
        gaps=tuple(gaps),
    )


def _gap_add(gaps: list[Gap], gap: Gap) -> None:
    """Append `gap`, joined to the one before when they touch and share their reason."""
    if gaps and gaps[-1].end + 1 == gap.start and gaps[-1].reason == gap.reason:
        before = gaps[-1]
        at = max((moment for moment in (before.at, gap.at) if moment is not None), default=None)
        gaps[-1] = Gap(before.start, gap.end, gap.reason, at)
    else:
        gaps.append(gap)


def streams_missing(completeness: Completeness) -> Iterable[Stream]:
    """The streams with numbers gone for no reason the portal knows: what the owner is warned
    of."""
    return [stream for stream in completeness.streams if stream.missing]
