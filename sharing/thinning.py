"""Thinning a series for display without changing its shape: at most `points` of its rows
([t, v1, v2...], oldest first, one per record), every kept row a whole record's (x and y never
from two records), the first and last always kept. The series answer says which method ran.

- `path` (a trajectory: the first two fields are x and y): largest-triangle-three-buckets
  (Steinarsson, 2013) along the path in capture order, in the x-y plane: the rows are cut into
  `points - 2` buckets, and of each the row that makes the largest triangle with the row kept
  before it and the mean of the next bucket (the path's turning point there) is kept. Only rows
  holding both x and y are on the path.
- `time` (each field over time): the time from the first row to the last cut in equal spans,
  and of each span the rows holding each field's lowest and highest value, with their times.
- `all`: every row, when they are `points` or fewer (on a path, every row holding x and y).
"""

from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum

Row = list[float | None]


class Shape(StrEnum):
    """What a plot draws, and so what its thinning keeps."""

    PATH = "path"
    TIME = "time"


class Method(StrEnum):
    """How a series' rows were thinned (the answer's `method`)."""

    ALL = "all"
    PATH = "largest-triangle-three-buckets"
    TIME = "min-max-per-time-bucket"


@dataclass(frozen=True)
class Thinned:
    rows: list[Row]
    method: Method


def path_rows(rows: Sequence[Row]) -> list[Row]:
    """The rows on a path: those holding both x and y (the first two fields) as numbers."""
    return [row for row in rows if len(row) > 2 and row[1] is not None and row[2] is not None]


def series_thinned(rows: Sequence[Row], *, points: int, shape: Shape) -> Thinned:
    """At most `points` (2 or more) of the rows, as `shape` draws them."""
    if points < 2:
        raise ValueError("a thinned series keeps at least its first and last row")
    kept = path_rows(rows) if shape == Shape.PATH else list(rows)
    if len(kept) <= points:
        return Thinned(kept, Method.ALL)
    if shape == Shape.PATH:
        return Thinned(path_thinned(kept, points), Method.PATH)
    return Thinned(time_thinned(kept, points), Method.TIME)


def path_thinned(rows: Sequence[Row], points: int) -> list[Row]:
    """Largest-triangle-three-buckets in the x-y plane: `points` of the rows (more than
    `points`, each holding x and y), the first and last among them, in order."""
    count = len(rows)
    buckets = points - 2
    if buckets == 0:
        return [rows[0], rows[-1]]
    size = (count - 2) / buckets
    kept = [0]
    for bucket in range(buckets):
        start, end = int(bucket * size) + 1, int((bucket + 1) * size) + 1
        following = rows[end : int((bucket + 2) * size) + 1] if bucket < buckets - 1 else []
        following = following or [rows[-1]]
        cx = sum(row[1] for row in following) / len(following)
        cy = sum(row[2] for row in following) / len(following)
        ax, ay = rows[kept[-1]][1], rows[kept[-1]][2]
        kept.append(
            max(
                range(start, end),
                key=lambda at: abs((ax - cx) * (rows[at][2] - ay) - (ax - rows[at][1]) * (cy - ay)),
            )
        )
    kept.append(count - 1)
    return [rows[at] for at in kept]


def time_thinned(rows: Sequence[Row], points: int) -> list[Row]:
    """At most `points` of the rows (oldest first): the first and last, and in each equal span
    of time the rows holding each field's lowest and highest value."""
    count = len(rows)
    width = max(len(rows[0]) - 1, 1)
    buckets = (points - 2) // (2 * width)
    kept = {0, count - 1}
    if buckets == 0:  # fewer points than two per field: the whole range's extremes that fit
        for at in sorted(_extremes(rows, range(count), width) - kept)[: points - len(kept)]:
            kept.add(at)
        return [rows[at] for at in sorted(kept)]
    first, span = rows[0][0], (rows[-1][0] - rows[0][0]) / buckets
    spans: list[list[int]] = [[] for _ in range(buckets)]
    for at, row in enumerate(rows):
        spans[min(int((row[0] - first) / span), buckets - 1) if span > 0 else 0].append(at)
    for members in spans:
        kept |= _extremes(rows, members, width)
    return [rows[at] for at in sorted(kept)]


def _extremes(rows: Sequence[Row], members: Sequence[int], width: int) -> set[int]:
    """Of the rows at `members`, those holding each field's lowest and highest value."""
    found: set[int] = set()
    for column in range(1, width + 1):
        valued = [at for at in members if column < len(rows[at]) and rows[at][column] is not None]
        if valued:
            found.add(min(valued, key=lambda at: rows[at][column]))
            found.add(max(valued, key=lambda at: rows[at][column]))
    return found
