"""The suite's tiers (tests/support/tiers.py): every test is in exactly one of the two parts
`make test` runs, the fast tier leaves out everything slow, and a process started unmarked is
caught."""

import itertools
import subprocess
from types import SimpleNamespace

import pytest

from tests.support import tiers

pytestmark = pytest.mark.nodb

MARKS = ("process", "browser", "slow", "bench", "nodb", "worker", "django_db")


def _every_mark_set():
    for size in range(len(MARKS) + 1):
        for combination in itertools.combinations(MARKS, size):
            yield set(combination)


def test_every_test_runs_in_exactly_one_part_of_the_full_suite():
    for marks in _every_mark_set():
        unit, once = tiers.TIERS["unit"](marks), tiers.TIERS["once"](marks)
        assert unit != once, marks


def test_the_fast_tier_is_unit_tests_without_the_benchmark_tooling():
    for marks in _every_mark_set():
        fast = tiers.TIERS["fast"](marks)
        assert fast == (tiers.TIERS["unit"](marks) and "bench" not in marks), marks
        assert not (fast and marks & {"process", "browser", "slow", "bench"}), marks


def test_postgresql_runs_again_only_the_unit_tests_that_use_the_database():
    for marks in _every_mark_set():
        again = tiers.TIERS["unit-db"](marks)
        assert again == (tiers.TIERS["unit"](marks) and not marks & {"nodb", "bench"}), marks


@pytest.mark.parametrize(
    ("fixture", "mark"),
    [("worker_stack", "process"), ("anvil", "process"), ("browser", "browser")],
)
def test_fixtures_that_start_processes_or_chromium_mark_their_tests(fixture, mark, request):
    item = SimpleNamespace(
        fixturenames=[fixture], path=request.path, marks=[], get_closest_marker=lambda _: None
    )
    item.add_marker = item.marks.append
    config = SimpleNamespace(rootpath=request.config.rootpath, getoption=lambda _: [])
    tiers.pytest_collection_modifyitems(config, [item])
    assert mark in {marker.name for marker in item.marks}


def test_a_process_started_by_an_unmarked_test_is_noted(monkeypatch):
    """The guard notes the command (and the report then fails the test); the session's own
    processes may start inside any test."""
    started = []
    monkeypatch.setattr(tiers, "_real_popen_init", lambda self, *a, **k: started.append(a))
    monkeypatch.setattr(tiers._state, "item", object(), raising=False)
    monkeypatch.setattr(tiers._state, "spawned", None, raising=False)
    with tiers.spawning_allowed():
        subprocess.Popen(["anvil"])
    assert tiers._state.spawned is None
    subprocess.Popen(["redis-server", "--port", "0"])
    assert tiers._state.spawned == ["redis-server", "--port", "0"]
    assert len(started) == 2  # the guard only looks: both were started
