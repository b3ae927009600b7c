"""What a gunicorn worker has done once it imported portal.wsgi, before its first request."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.nodb


def test_a_worker_imports_every_view_at_boot_and_keeps_its_database_connections():
    program = (
        "import sys, json, portal.wsgi\n"
        "from django.conf import settings\n"
        "print(json.dumps({'views': [m for m in ('sharing.apis', 'accounts.views', "
        "'rest_framework.views') if m in sys.modules], "
        "'max_age': settings.DATABASES['default']['CONN_MAX_AGE'], "
        "'health': settings.DATABASES['default']['CONN_HEALTH_CHECKS']}))"
    )
    environment = {k: v for k, v in os.environ.items() if k != "DATABASE_CONN_MAX_AGE"}
    done = subprocess.run(
        [sys.executable, "-c", program],
        cwd=REPO_ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    booted = json.loads(done.stdout.strip().splitlines()[-1])
    assert booted["views"] == ["sharing.apis", "accounts.views", "rest_framework.views"]
    assert booted["max_age"] > 0
    assert booted["health"] is True
