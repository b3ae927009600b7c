"""What a web worker has done once it imported portal.wsgi, before its first request."""

import json

import pytest

from tests.fresh_python import fresh_python

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
    booted = json.loads(fresh_python(program, unset=["DATABASE_CONN_MAX_AGE"]))
    assert booted["views"] == ["sharing.apis", "accounts.views", "rest_framework.views"]
    assert booted["max_age"] > 0
    assert booted["health"] is True


def test_a_worker_keeps_what_its_boot_made_out_of_the_collectors_walks():
    program = "import gc, portal.wsgi\nprint(gc.get_freeze_count())"
    frozen = int(fresh_python(program))
    assert frozen > 100_000  # Django, DRF, web3 and the portal's modules: hundreds of thousands
