"""The suite's tiers, and a guard that keeps them honest (loaded by `-p tests.support.tiers`).

A test is marked by what it needs beyond this process, Redis and the session's anvil:

- ``process``: starts processes (Celery workers, web servers, a node of its own, a ROS master,
  SeaweedFS, ``manage.py`` or the agent as commands). Marked by its fixtures (_PROCESS_FIXTURES)
  or by hand. A test that starts a process without the mark fails (the guard below), so a new
  one cannot slip into the fast tier unnoticed.
- ``browser``: drives Chromium (the ``browser`` fixture marks it).
- ``slow``: a long run in this process (the API fuzz run).
- ``bench``: tests of the benchmark tooling (tests/bench/).
- ``nodb``: never touches the database (tests/conftest.py's list).

`--tier` picks a part of the suite (scripts/test.sh), given again for several; without it pytest
runs every test:

- ``fast``: none of process, browser, slow and bench (`make test-fast`, in parallel).
- ``unit``: none of process, browser and slow (`make test`'s SQLite pass, bench included).
- ``unit-db``: the unit tests that use the database, without bench (`make test`'s PostgreSQL
  pass runs them again there).
- ``once``: process, browser and slow (`make test` runs them once, on PostgreSQL).

``unit`` and ``once`` together are the whole suite: no test is in neither.
"""

from __future__ import annotations

import subprocess
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

_ONCE = ("process", "browser", "slow")
TIERS = {
    "fast": lambda marks: not marks & {*_ONCE, "bench"},
    "unit": lambda marks: not marks & set(_ONCE),
    "unit-db": lambda marks: not marks & {*_ONCE, "bench", "nodb"},
    "once": lambda marks: bool(marks & set(_ONCE)),
}

_PROCESS_FIXTURES = frozenset(
    {"worker_stack", "stack", "anvil", "fresh_chain", "ros_master", "seaweedfs"}
)
_BROWSER_FIXTURES = frozenset({"browser"})
_MARKS_THAT_ALLOW_PROCESSES = ("process", "browser")

# The test running now, while a spawn would break its tier; None outside tests and while
# spawning is allowed (the session's own anvil).
_state = threading.local()
_real_popen_init = subprocess.Popen.__init__


def _guarded_popen_init(self: subprocess.Popen, *args: Any, **kwargs: Any) -> None:
    item = getattr(_state, "item", None)
    if item is not None and not getattr(_state, "allowed", False):
        command = args[0] if args else kwargs.get("args")
        _state.spawned = command
    _real_popen_init(self, *args, **kwargs)


@contextmanager
def spawning_allowed() -> Iterator[None]:
    """Processes the suite itself needs (the session's anvil) may start inside any test."""
    _state.allowed = True
    try:
        yield
    finally:
        _state.allowed = False


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--tier",
        action="append",
        choices=sorted(TIERS),
        default=[],
        help=(
            "run a tier of the suite, or several given again (tests/support/tiers.py); "
            "all without it"
        ),
    )


def pytest_configure(config: pytest.Config) -> None:
    subprocess.Popen.__init__ = _guarded_popen_init  # type: ignore[method-assign]


def pytest_unconfigure(config: pytest.Config) -> None:
    subprocess.Popen.__init__ = _real_popen_init  # type: ignore[method-assign]


@pytest.hookimpl(trylast=True)  # after tests/conftest.py has marked nodb
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    root = str(config.rootpath) + "/"
    for item in items:
        fixtures = set(getattr(item, "fixturenames", ()))
        if fixtures & _BROWSER_FIXTURES:
            item.add_marker(pytest.mark.browser)
        if fixtures & _PROCESS_FIXTURES or item.get_closest_marker("worker"):
            item.add_marker(pytest.mark.process)
        if str(item.path).removeprefix(root).startswith("tests/bench/"):
            item.add_marker(pytest.mark.bench)
    # The long runs first, then the tests that start processes (seconds each), then the rest:
    # started last, a long one would hold a worker after the others end, while short ones
    # fill the last gaps. The sort is stable: within each group, the order of collection.
    items.sort(key=_long_first)
    tiers = [TIERS[name] for name in config.getoption("tier")]
    if not tiers:
        return
    selected, deselected = [], []
    for item in items:
        marks = {mark.name for mark in item.iter_markers()}
        (selected if any(keep(marks) for keep in tiers) else deselected).append(item)
    if deselected:
        config.hook.pytest_deselected(items=deselected)
        items[:] = selected


def _long_first(item: pytest.Item) -> tuple[bool, bool]:
    starts_processes = any(item.get_closest_marker(mark) for mark in ("process", "browser"))
    return item.get_closest_marker("slow") is None, not starts_processes


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> object:
    """Watch the test (setup, call and teardown) for processes it starts unmarked."""
    may_spawn = any(item.get_closest_marker(mark) for mark in _MARKS_THAT_ALLOW_PROCESSES)
    _state.item = None if may_spawn else item
    _state.spawned = None
    try:
        return (yield)
    finally:
        _state.item = None


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> pytest.TestReport:
    report = yield
    spawned = getattr(_state, "spawned", None)
    if report.when == "call" and spawned is not None and _state.item is item:
        report.outcome = "failed"
        report.longrepr = (
            f"{item.nodeid} started a process ({spawned!r}) without the `process` mark: "
            "mark it (pytestmark = pytest.mark.process) so that it leaves the fast tier "
            "(tests/support/tiers.py)"
        )
    return report
