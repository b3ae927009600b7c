"""The batching settings a process reads at start: nonsense stops it with the setting named."""

import os
import subprocess
import sys

import pytest

from stack.processes import REPO_ROOT

pytestmark = pytest.mark.nodb


def _settings_with(**environment: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", "import portal.settings as s; print(s.ANCHOR_QUIET)"],
        cwd=REPO_ROOT,
        env={**os.environ, **environment},
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


@pytest.mark.parametrize("name", ["ANCHOR_QUIET", "ANCHOR_MAX_WAIT"])
def test_a_negative_wait_is_refused_at_start(name):
    started = _settings_with(**{name: "-0.1"})
    assert started.returncode != 0
    assert "ANCHOR_MAX_WAIT and ANCHOR_QUIET must not be negative" in started.stderr


def test_the_pause_that_closes_a_batch_is_read_from_the_environment():
    assert _settings_with(ANCHOR_QUIET="0").stdout.strip() == "0.0"
    assert _settings_with(ANCHOR_QUIET="0.25").stdout.strip() == "0.25"
