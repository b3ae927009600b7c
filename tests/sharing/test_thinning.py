"""Thinning a series for display (sharing/thinning.py): every kept point is one record of the
input (x and y from the same record), in order, the first and last kept, never more than asked;
a path keeps the shape of a figure-8 where per-field extremes draw a diamond; a time plot keeps
each field's spikes."""

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sharing.thinning import Method, Shape, path_rows, series_thinned

values = st.one_of(st.none(), st.floats(min_value=-1e6, max_value=1e6, allow_nan=False))


@st.composite
def series_rows(draw: st.DrawFn) -> list[list[float | None]]:
    """Rows [t, v1...vk] in time order (times may repeat), as the series answers them."""
    width = draw(st.integers(min_value=1, max_value=4))
    steps = draw(st.lists(st.integers(min_value=0, max_value=3), min_size=0, max_size=400))
    rows, t = [], 1_764_380_000.0
    for step in steps:
        t += step * 0.05
        rows.append([t, *draw(st.lists(values, min_size=width, max_size=width))])
    return rows


def _is_subsequence(kept: list[list[float | None]], rows: list[list[float | None]]) -> bool:
    """Each kept row is the very row (object) of the input, in the input's order, none twice."""
    at = 0
    for row in kept:
        while at < len(rows) and rows[at] is not row:
            at += 1
        if at == len(rows):
            return False
        at += 1
    return True


@settings(max_examples=200, deadline=None)
@given(
    rows=series_rows(), points=st.integers(min_value=2, max_value=60), shape=st.sampled_from(Shape)
)
def test_every_kept_point_is_a_record_of_the_input_first_and_last_kept(rows, points, shape):
    thinned = series_thinned(rows, points=points, shape=shape)
    candidates = path_rows(rows) if shape == Shape.PATH else rows
    assert _is_subsequence(thinned.rows, candidates)
    assert len(thinned.rows) <= points
    if candidates:
        assert thinned.rows[0] is candidates[0]
        assert thinned.rows[-1] is candidates[-1]
    if len(candidates) <= points:
        assert (thinned.method, thinned.rows) == (Method.ALL, candidates)
    else:
        assert thinned.method == (Method.PATH if shape == Shape.PATH else Method.TIME)
        if shape == Shape.PATH:
            assert len(thinned.rows) == points  # one per bucket: the budget is spent on the path


def _figure_eight(count: int) -> list[list[float | None]]:
    """A robot driving a figure-8 (the simulator's lemniscate) for `count` records at 10 Hz."""
    rows = []
    for i in range(count):
        a = 2 * math.pi * i / 600  # a loop a minute
        rows.append([i / 10, 3 * math.sin(a), 3 * math.sin(a) * math.cos(a)])
    return rows


def _distance_to_path(point: list[float | None], path: list[list[float | None]]) -> float:
    return min(math.hypot(point[1] - p[1], point[2] - p[2]) for p in path)


def _distance_to_segment(point: list[float | None], a: list[float | None], b: list[float | None]):
    dx, dy = b[1] - a[1], b[2] - a[2]
    length = dx * dx + dy * dy
    along = 0.0 if length == 0 else ((point[1] - a[1]) * dx + (point[2] - a[2]) * dy) / length
    along = min(max(along, 0.0), 1.0)
    return math.hypot(point[1] - a[1] - along * dx, point[2] - a[2] - along * dy)


def test_a_thinned_figure_eight_stays_on_its_path_and_draws_it_whole():
    rows = _figure_eight(18_000)  # 30 minutes
    thinned = series_thinned(rows, points=1000, shape=Shape.PATH)
    assert thinned.method == Method.PATH
    assert len(thinned.rows) == 1000
    assert all(any(row is kept for row in rows) for kept in thinned.rows[:50])
    # Each segment drawn between two kept points stays near the path (no chords across the
    # loops): its midpoint is within 5 cm of some record of the path.
    one_loop = rows[:600]
    for a, b in itertools.pairwise(thinned.rows):
        middle = [None, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2]
        assert _distance_to_path(middle, one_loop) < 0.05
    # Every part of the path is drawn: each record is within 5 cm of the line drawn.
    drawn = list(itertools.pairwise(thinned.rows[:60]))
    for record in one_loop:
        assert min(_distance_to_segment(record, a, b) for a, b in drawn) < 0.05


def test_per_field_extremes_would_not_keep_the_figure_eight():
    """Why a path is not thinned per field: the time shape keeps x and y extremes, whose
    segments cut across the loops (the diamond seen on a 30-minute plot)."""
    rows = _figure_eight(18_000)
    kept = series_thinned(rows, points=1000, shape=Shape.TIME).rows
    one_loop = rows[:600]
    far = max(
        _distance_to_path([None, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2], one_loop)
        for a, b in itertools.pairwise(kept)
    )
    path_kept = series_thinned(rows, points=1000, shape=Shape.PATH).rows
    path_far = max(
        _distance_to_path([None, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2], one_loop)
        for a, b in itertools.pairwise(path_kept)
    )
    assert far > 0.25  # chords a quarter of a metre off the path, on a 3 m figure-8
    assert path_far < 0.05


def test_time_thinning_keeps_each_buckets_extremes_with_their_times():
    rows = [[float(t), 0.0, float(t % 7)] for t in range(10_000)]
    rows[4321][1] = 1000.0  # a spike: kept
    rows[8765][1] = -1000.0  # a dip: kept
    thinned = series_thinned(rows, points=500, shape=Shape.TIME)
    assert thinned.method == Method.TIME
    assert len(thinned.rows) <= 500
    assert rows[4321] in thinned.rows
    assert rows[8765] in thinned.rows
    assert (thinned.rows[0], thinned.rows[-1]) == (rows[0], rows[-1])
    assert thinned.rows == sorted(thinned.rows)  # in time order, whole rows


def test_time_buckets_are_spans_of_time_not_of_rows():
    """A burst of records and a quiet stretch: the quiet stretch's extremes are kept though it
    holds few of the rows."""
    burst = [[i / 1000, 0.0] for i in range(9_000)]  # 9 s
    quiet = [[10.0 + i, float(i % 5)] for i in range(1000)]  # 1000 s, one a second
    quiet[500][1] = 99.0
    thinned = series_thinned(burst + quiet, points=102, shape=Shape.TIME)
    assert quiet[500] in thinned.rows
    assert sum(1 for row in thinned.rows if row[0] < 10.0) <= 4


def test_a_path_is_drawn_through_the_records_holding_both_x_and_y():
    rows = [[0.0, 1.0, 1.0], [1.0, None, 2.0], [2.0, 3.0, None], [3.0, 4.0, 4.0]]
    thinned = series_thinned(rows, points=10, shape=Shape.PATH)
    assert (thinned.method, thinned.rows) == (Method.ALL, [rows[0], rows[3]])


def test_fewer_than_two_points_is_refused():
    with pytest.raises(ValueError, match="at least"):
        series_thinned([[0.0, 1.0]], points=1, shape=Shape.TIME)
