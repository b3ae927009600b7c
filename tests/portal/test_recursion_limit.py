"""Deeply nested JSON from a client raises an error instead of killing the process."""

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.process

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_nested_json_raises_instead_of_crashing():
    program = (
        "import django, os; os.environ['DJANGO_SETTINGS_MODULE'] = 'portal.settings'; "
        "django.setup(); import web3, json\n"
        "try:\n    json.loads('[' * 200000)\nexcept RecursionError:\n    print('refused')"
    )
    done = subprocess.run(
        [sys.executable, "-c", program],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "refused"
