"""Imports go down the layers (docs/architecture.md), never up or round in a circle.

Read from the source with `ast`, so the test needs nothing running and fails on the import
that breaks the rule, wherever in a file it is written. A task sent by name through the outbox
(`enqueue("sharing.tasks.records_anchor", ...)`) is read too: it calls into its app as an
import would.
"""

import ast
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.source_imports import REPO_ROOT, imports, source_files

pytestmark = pytest.mark.nodb

PACKAGES = (
    "portal",
    "accounts",
    "sharing",
    "alerts",
    "chainworker",
    "core",
    "smcrypto",
    "ros_agent",
    "authros_verify",
)
# What each package may import of the others; everything not listed is forbidden.
ALLOWED = {
    "portal": {"accounts", "sharing", "alerts", "chainworker", "core", "smcrypto"},
    "sharing": {"accounts", "alerts", "chainworker", "core", "smcrypto", "authros_verify"},
    # Told of events by sharing; reads owners and robots through accounts.
    "alerts": {"accounts", "chainworker", "core", "smcrypto"},
    "accounts": {"chainworker", "core", "smcrypto"},
    "chainworker": {"core", "smcrypto"},
    "core": set(),
    "smcrypto": set(),
    "ros_agent": {"smcrypto"},
    # The standalone verifier of exports: anyone runs it without the portal.
    "authros_verify": {"smcrypto"},
}
# Where a function-level import of the project's own modules is the rule, not a dodge:
# AppConfig.ready runs once models can be imported; a command (`authros-agent`) loads only the
# subcommand it runs: the ROS 1 node needs rospy, which a ROS 2 robot does not have.
LOCAL_IMPORTS_ALLOWED = {"apps.py", "__main__.py"}
# core.outbox's functions that send a task by its registered name, "<module>.tasks.<name>".
SENDS_A_TASK = {"enqueue", "dispatch"}
TASK_NAME = re.compile(r"\w+(\.\w+)*\.tasks\.\w+")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO_ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _tasks_sent(path: Path) -> Iterator[tuple[str, int]]:
    """(module of the task, line) for each task the file sends by a name written out in it."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call) or not node.args:
            continue
        # enqueue(...) or outbox.enqueue(...)
        called = getattr(node.func, "id", None) or getattr(node.func, "attr", None)
        name = node.args[0]
        if (
            called in SENDS_A_TASK
            and isinstance(name, ast.Constant)
            and isinstance(name.value, str)
            and TASK_NAME.fullmatch(name.value)
        ):
            yield name.value.rpartition(".")[0], node.lineno


def _project_module(name: str, modules: set[str]) -> str | None:
    """The longest project module that `name` (a module or module.attribute) lies in."""
    parts = name.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


def _graph() -> tuple[dict[str, set[str]], list[str]]:
    files = {_module_name(path): path for package in PACKAGES for path in source_files(package)}
    modules = set(files)
    edges: dict[str, set[str]] = {module: set() for module in modules}
    local: list[str] = []
    for module, path in files.items():
        for name, is_local, line in imports(path):
            target = _project_module(name, modules)
            if target is None or target == module:
                continue
            edges[module].add(target)
            if is_local and path.name not in LOCAL_IMPORTS_ALLOWED:
                local.append(f"{path.relative_to(REPO_ROOT)}:{line} imports {target}")
    return edges, local


def _task_graph() -> dict[str, set[str]]:
    """Which project modules each module sends tasks of, by name."""
    files = {_module_name(path): path for package in PACKAGES for path in source_files(package)}
    modules = set(files)
    sent: dict[str, set[str]] = {module: set() for module in modules}
    for module, path in files.items():
        for name, _line in _tasks_sent(path):
            target = _project_module(name, modules)
            if target is not None:
                sent[module].add(target)
    return sent


def _across_the_layers(graph: dict[str, set[str]], verb: str) -> list[str]:
    """The arrows of `graph` from one package to another that ALLOWED does not list."""
    return sorted(
        f"{module} {verb} {target}"
        for module, targets in graph.items()
        for target in targets
        if (package := module.split(".")[0]) != (other := target.split(".")[0])
        and other not in ALLOWED[package]
    )


def test_packages_import_only_the_layers_below_them():
    edges, _local = _graph()
    assert _across_the_layers(edges, "imports") == []


def test_packages_send_tasks_only_of_the_layers_below_them():
    """A service sends its own app's tasks and those of the layers below by name, never one of
    an app above (that app registers with the one below instead). Not part of the circle
    check: a task imports its service and the service sends it by name, as the outbox means."""
    assert _across_the_layers(_task_graph(), "sends a task of") == []


def test_no_module_imports_the_project_inside_a_function():
    _edges, local = _graph()
    assert local == []


def test_no_import_circle_between_modules():
    edges, _local = _graph()
    state: dict[str, str] = {}
    circles: list[list[str]] = []

    def visit(module: str, path: list[str]) -> None:
        state[module] = "open"
        for target in sorted(edges[module]):
            if state.get(target) == "open":
                circles.append([*path[path.index(target) :], target])
            elif target not in state:
                visit(target, [*path, target])
        state[module] = "done"

    for module in sorted(edges):
        if module not in state:
            visit(module, [module])
    assert circles == []


def test_the_check_sees_a_forbidden_import(tmp_path):
    """The reading above finds imports at any depth, so the rules cannot pass vacuously."""
    source = tmp_path / "probe.py"
    source.write_text("import os\n\ndef f():\n    from sharing import services\n")
    assert list(imports(source)) == [("os", False, 1), ("sharing.services", True, 4)]
    edges, _local = _graph()
    assert "chainworker.client" in edges["sharing.services.anchoring"]


def test_the_check_sees_a_task_sent_by_name(tmp_path):
    """Task names written out in a call to enqueue or dispatch, at any depth; not a name in a
    variable, nor a string that is no task name."""
    source = tmp_path / "probe.py"
    source.write_text(
        "from core import outbox\n"
        "def f(name):\n"
        "    on_commit(lambda: enqueue('sharing.tasks.records_anchor', 1))\n"
        "    outbox.dispatch('accounts.tasks.key_rotate', 2, countdown=1)\n"
        "    enqueue(name)\n"
        "    enqueue('no task')\n"
    )
    assert sorted(_tasks_sent(source), key=lambda sent: sent[1]) == [
        ("sharing.tasks", 3),
        ("accounts.tasks", 4),
    ]
    assert "accounts.tasks" in _task_graph()["sharing.services.grant_chain"]


# What the standalone verifier may never load: Django, its ecosystem, or a portal app.
NOT_FOR_THE_VERIFIER = {"django", "rest_framework", "drf_spectacular", "celery", "kombu", "redis"}


def test_the_export_verifier_needs_neither_django_nor_the_portal():
    """authros_verify runs where the portal does not: of the project it imports smcrypto
    only, and neither it nor smcrypto imports Django or its ecosystem (the command's test in
    tests/authros_verify also checks the modules a real run loads)."""
    edges, _local = _graph()
    from_verifier = {
        target.split(".")[0]
        for module, targets in edges.items()
        if module.startswith("authros_verify")
        for target in targets
    }
    assert from_verifier <= {"authros_verify", "smcrypto"}
    third_party = {
        name.split(".")[0]
        for package in ("authros_verify", "smcrypto")
        for path in source_files(package)
        for name, _is_local, _line in imports(path)
    }
    assert not third_party & NOT_FOR_THE_VERIFIER
