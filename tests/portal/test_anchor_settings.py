"""The batching settings a process reads at start: nonsense stops it with the setting named."""

import subprocess

import pytest

from tests.support.fresh_python import fresh_python_run

pytestmark = [pytest.mark.process, pytest.mark.nodb]


def _settings_with(**environment: str) -> subprocess.CompletedProcess[str]:
    return fresh_python_run("import portal.settings as s; print(s.ANCHOR_QUIET)", env=environment)


@pytest.mark.parametrize("name", ["ANCHOR_QUIET", "ANCHOR_MAX_WAIT"])
def test_a_negative_wait_is_refused_at_start(name):
    started = _settings_with(**{name: "-0.1"})
    assert started.returncode != 0
    assert "ANCHOR_MAX_WAIT and ANCHOR_QUIET must not be negative" in started.stderr


def test_the_pause_that_closes_a_batch_is_read_from_the_environment():
    assert _settings_with(ANCHOR_QUIET="0").stdout.strip() == "0.0"
    assert _settings_with(ANCHOR_QUIET="0.25").stdout.strip() == "0.25"
