"""Every record counted (DESIGN.md "Provenance v2"), as an export's reader checks it: per stream
(signer, topic), the first and last `topic_seq`, the count, and every gap, from the records
that verified, each counted by the `topic_seq` its robot signed (its anchored envelope's
header), never by what the bundle says of it.

The portal's own completeness for the selection (the bundle's `streams`) and its `excluded`
list only name gaps: a number no verified record holds is a gap whatever the portal says, and
takes the portal's reason (`deleted`, `retention`, both with when, or `missing`), or
`excluded` (a record the export left out, and why) when the bundle gives one, else `missing`.
The portal's first and last widen a stream (the numbers it claims the window holds and the
export does not are gaps too); they never narrow it.

Gaps are kept as ranges, never number by number, so a portal that claims a range of a billion
costs nothing to report.
"""

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

MISSING = "missing"
EXCLUDED = "excluded"
PORTAL_REASONS = ("missing", "deleted", "retention")
_STREAM_FIELDS = {"signer", "topic", "robot", "first", "last", "count", "gaps"}
_GAP_FIELDS = {"from", "to", "reason"}


class StreamsMalformed(ValueError):
    """The bundle's `streams` is not the portal's completeness answer."""


@dataclass(frozen=True)
class Gap:
    start: int
    end: int
    reason: str  # missing, deleted, retention or excluded
    detail: str = ""  # when it was deleted, or why the export left the record out

    @property
    def size(self) -> int:
        return self.end - self.start + 1

    def as_json(self) -> dict[str, object]:
        answer: dict[str, object] = {"from": self.start, "to": self.end, "reason": self.reason}
        if self.detail:
            answer["detail"] = self.detail
        return answer


@dataclass(frozen=True)
class StreamReport:
    signer: str
    topic: str
    robot: str
    first: int | None  # None: the export holds none of the numbers the portal claims
    last: int | None
    count: int
    gaps: tuple[Gap, ...] = field(default=())

    def as_json(self) -> dict[str, object]:
        return {
            "signer": self.signer,
            "topic": self.topic,
            "robot": self.robot,
            "first": self.first,
            "last": self.last,
            "count": self.count,
            "gaps": [gap.as_json() for gap in self.gaps],
        }


@dataclass(frozen=True)
class _Claimed:
    """What the portal says of one stream: its range, and its gaps' reasons."""

    robot: str
    first: int
    last: int
    gaps: tuple[Gap, ...]


class StreamTally:
    """The verified records' signed (signer, topic, topic_seq), one entry each."""

    def __init__(self) -> None:
        self._numbers: dict[tuple[str, str], dict[int, int]] = {}
        self._robots: dict[tuple[str, str], str] = {}

    def add(self, *, signer: str, topic: str, robot: str, topic_seq: int, index: int) -> int | None:
        """Count a record (its index in the bundle); the index of the record counted before
        with the same number of the same stream, if one was (the number is reused)."""
        key = (signer, topic)
        numbers = self._numbers.setdefault(key, {})
        self._robots.setdefault(key, robot)
        before = numbers.get(topic_seq)
        if before is None:
            numbers[topic_seq] = index
        return before

    def reports(
        self, portal: Mapping[str, Any] | None, excluded: Iterable[Any]
    ) -> list[StreamReport]:
        """Each stream, the verified ones and those the portal claims, sorted by signer and
        topic. StreamsMalformed if `portal` (the bundle's `streams`) is not well formed."""
        claims = _claims(portal)
        left_out = _excluded(excluded)
        reports = []
        for key in sorted(set(self._numbers) | set(claims)):
            numbers = sorted(self._numbers.get(key, {}))
            claimed = claims.get(key)
            robot = self._robots.get(key) or (claimed.robot if claimed else "")
            labels = sorted(
                [*(claimed.gaps if claimed else ()), *left_out.get(key, ())],
                key=lambda gap: gap.start,
            )
            holes = _holes(numbers, claimed)
            gaps = tuple(_merged(labelled for hole in holes for labelled in _split(hole, labels)))
            reports.append(
                StreamReport(
                    signer=key[0],
                    topic=key[1],
                    robot=robot,
                    first=numbers[0] if numbers else None,
                    last=numbers[-1] if numbers else None,
                    count=len(numbers),
                    gaps=gaps,
                )
            )
        return reports


def _holes(numbers: list[int], claimed: _Claimed | None) -> list[tuple[int, int]]:
    """The ranges of numbers no verified record holds, between the first and the last of the
    verified records and of the portal's claim."""
    holes = []
    low = min([*numbers[:1], *([claimed.first] if claimed else [])])
    high = max([*numbers[-1:], *([claimed.last] if claimed else [])])
    expected = low
    for number in numbers:
        if number > expected:
            holes.append((expected, number - 1))
        expected = number + 1
    if high >= expected:
        holes.append((expected, high))
    return holes


def _split(hole: tuple[int, int], labels: list[Gap]) -> list[Gap]:
    """The hole in ranges of one reason: the labels' where they cover it (the first label
    wins where two overlap), `missing` elsewhere."""
    start, end = hole
    parts: list[Gap] = []
    at = start
    for label in labels:
        if label.end < at or label.start > end:
            continue
        if label.start > at:
            parts.append(Gap(at, label.start - 1, MISSING))
        upto = min(label.end, end)
        parts.append(Gap(max(at, label.start), upto, label.reason, label.detail))
        at = upto + 1
        if at > end:
            return parts
    parts.append(Gap(at, end, MISSING))
    return parts


def _merged(gaps: Iterable[Gap]) -> list[Gap]:
    merged: list[Gap] = []
    for gap in gaps:
        touching = merged and merged[-1].end + 1 == gap.start
        if touching and merged[-1].reason == gap.reason == MISSING:
            merged[-1] = Gap(merged[-1].start, gap.end, MISSING)
        else:
            merged.append(gap)
    return merged


def _whole(value: Any) -> bool:
    return type(value) is int and value >= 0


def _claims(portal: Mapping[str, Any] | None) -> dict[tuple[str, str], _Claimed]:
    if portal is None:
        return {}
    streams = portal.get("streams") if isinstance(portal, Mapping) else None
    if (
        not isinstance(portal, Mapping)
        or set(portal) != {"streams", "uncounted"}
        or not isinstance(streams, list)
        or not _whole(portal["uncounted"])
    ):
        raise StreamsMalformed("it is not an object of `streams` and `uncounted`")
    claims: dict[tuple[str, str], _Claimed] = {}
    for stream in streams:
        if not isinstance(stream, Mapping) or set(stream) != _STREAM_FIELDS:
            raise StreamsMalformed(f"a stream's fields are not {sorted(_STREAM_FIELDS)}")
        signer, topic, robot = stream["signer"], stream["topic"], stream["robot"]
        first, last, gaps = stream["first"], stream["last"], stream["gaps"]
        if not all(isinstance(text, str) for text in (signer, topic, robot)):
            raise StreamsMalformed("a stream's signer, topic and robot are not texts")
        if not (_whole(first) and _whole(last) and first <= last and _whole(stream["count"])):
            raise StreamsMalformed(f"stream ({signer}, {topic}) has no range first..last")
        if not isinstance(gaps, list) or (signer, topic) in claims:
            raise StreamsMalformed(f"stream ({signer}, {topic}) is stated twice or has no gaps")
        claims[signer, topic] = _Claimed(robot, first, last, tuple(_claimed_gap(g) for g in gaps))
    return claims


def _claimed_gap(gap: Any) -> Gap:
    if not isinstance(gap, Mapping) or not _GAP_FIELDS <= set(gap) <= {*_GAP_FIELDS, "at"}:
        raise StreamsMalformed(f"a gap's fields are not {sorted(_GAP_FIELDS)} (and `at`)")
    start, end, reason, at = gap["from"], gap["to"], gap["reason"], gap.get("at")
    if not (_whole(start) and _whole(end) and start <= end and reason in PORTAL_REASONS):
        raise StreamsMalformed("a gap is not a range from..to with a reason the portal gives")
    if at is not None and not isinstance(at, str):
        raise StreamsMalformed("a gap's `at` is not a time")
    return Gap(start, end, reason, f"at {at}" if at else "")


def _excluded(entries: Iterable[Any]) -> dict[tuple[str, str], list[Gap]]:
    """The records the export left out that name their stream and number (a v3 bundle's)."""
    left_out: dict[tuple[str, str], list[Gap]] = {}
    for entry in entries:
        if not isinstance(entry, Mapping):
            continue
        signer, topic, number = entry.get("signer"), entry.get("topic"), entry.get("topic_seq")
        if isinstance(signer, str) and isinstance(topic, str) and _whole(number):
            why = f"{entry.get('reason')}: record {entry.get('record')}"
            left_out.setdefault((signer, topic), []).append(Gap(number, number, EXCLUDED, why))
    return left_out
