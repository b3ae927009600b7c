"""What a web worker has done once it imported portal.wsgi, before its first request."""

import json

import pytest

from tests.support.fresh_python import fresh_python, fresh_python_run

pytestmark = [pytest.mark.process, pytest.mark.nodb]


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


def test_a_worker_loads_neither_a_test_chain_nor_opencv():
    """eth-tester (py-evm) is a test chain the runtime never uses, OpenCV is for the images of
    an MCAP export in the worker: together about 1 s of CPU and 26 MiB in every web and worker
    process that loaded them at boot."""
    program = (
        "import sys, json, portal.wsgi\n"
        "print(json.dumps(sorted(m for m in ('eth_tester', 'eth', 'cv2') if m in sys.modules)))"
    )
    assert json.loads(fresh_python(program)) == []


def test_a_worker_keeps_what_its_boot_made_out_of_the_collectors_walks():
    program = "import gc, portal.wsgi\nprint(gc.get_freeze_count())"
    frozen = int(fresh_python(program))
    assert frozen > 100_000  # Django, DRF, web3 and the portal's modules: hundreds of thousands


def test_a_request_carries_none_of_the_servers_environment():
    """A server that starts each request's environ from a copy of the process's environment
    (as CGI does, and granian did; secrets included): the portal sees only what the request
    and the server set. The environ handed to portal.wsgi.application is the one Django sees,
    so what is left in it afterwards is what the portal saw."""
    program = """
import io, json, os
import portal.wsgi

scope = {
    "REQUEST_METHOD": "GET", "PATH_INFO": "/api/", "QUERY_STRING": "", "SCRIPT_NAME": "",
    "SERVER_NAME": "127.0.0.1", "SERVER_PORT": "8000", "SERVER_PROTOCOL": "HTTP/1.1",
    "REMOTE_ADDR": "127.0.0.1", "HTTP_HOST": "127.0.0.1", "HTTP_X_ROBOT_NOTE": "from the request",
    "wsgi.url_scheme": "http", "wsgi.input": io.BytesIO(b""), "wsgi.errors": io.StringIO(),
    "wsgi.version": (1, 0), "wsgi.multithread": True, "wsgi.multiprocess": True,
    "wsgi.run_once": False,
}
environ = {**os.environ, **scope}
statuses = []
body = portal.wsgi.application(environ, lambda status, headers: statuses.append(status))
b"".join(body)
print(json.dumps({
    "status": int(statuses[0].split()[0]),
    "from_process": sorted(k for k in os.environ if k in environ and k not in scope),
    "header": environ.get("HTTP_X_ROBOT_NOTE"),
    "method": environ.get("REQUEST_METHOD"),
}))
"""
    done = fresh_python_run(
        program,
        env={"AUTHROS_PROBE_SECRET": "s3cret", "HTTP_X_OPERATOR_NOTE": "not a request header"},
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    # Only the keys a server sets itself (it sets these to its own values) are left.
    assert set(seen["from_process"]) <= {"GATEWAY_INTERFACE", "SERVER_SOFTWARE"}
    assert seen["header"] == "from the request"
    assert seen["method"] == "GET"
    assert seen["status"] == 404  # the request itself was served
