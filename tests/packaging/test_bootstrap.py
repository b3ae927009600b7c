"""`make run` installs only what running needs; the test tooling (PostgreSQL, which Debian
starts a cluster of, Chromium, systemd's analyzer, and the Python packages of the tests:
Playwright, pytest, ...) comes with `make test` alone. What each locked set holds is
tests/packaging/test_imports.py's."""

import subprocess

import pytest

from tests.support.harness import REPO_ROOT

pytestmark = [pytest.mark.nodb, pytest.mark.process]

TEST_TOOLING = {"postgresql", "postgresql-client", "chromium", "systemd"}
# The locked sets of Python packages: make run's, and make test's (which holds it).
RUN_SET, DEV_SET = "requirements/run.txt", "requirements/dev.txt"


def packages(*arguments: str) -> set[str]:
    done = subprocess.run(
        ["bash", "scripts/bootstrap.sh", *arguments, "--list"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=30, check=True,
    )  # fmt: skip
    return set(done.stdout.split())


def test_make_run_installs_no_test_tooling_and_make_test_does():
    running = packages()
    assert {"redis-server", "python3-rospy", "ros-core", RUN_SET} <= running
    assert not TEST_TOOLING & running
    assert DEV_SET not in running
    assert packages("--test") == (running - {RUN_SET}) | TEST_TOOLING | {DEV_SET}
    assert "bash scripts/bootstrap.sh --test" in (REPO_ROOT / "scripts/test.sh").read_text()
    assert "bash scripts/bootstrap.sh\n" in (REPO_ROOT / "scripts/run.sh").read_text()
