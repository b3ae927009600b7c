"""A host that runs only workers serves /metrics on WORKER_METRICS_PORT (portal/worker_metrics.py):
the web's view, with its token rule, and nothing else on the port. A real worker serving it is
tests/stack/test_workers_seen.py's."""

import io
import socket
from wsgiref.util import setup_testing_defaults

import pytest
import requests

from portal.celery import app
from portal.worker_metrics import worker_metrics_app, worker_metrics_serve
from stack.anvil import free_port
from tests.support.logs import logged_by

pytestmark = pytest.mark.django_db

TOKEN = "metrics-token-for-the-test"


def _get(path: str, *, remote: str = "127.0.0.1", method: str = "GET", **headers: str):
    """(status line, headers, body) of one request to the port's WSGI application."""
    environ = {"PATH_INFO": path, "REMOTE_ADDR": remote, "REQUEST_METHOD": method}
    environ.update({f"HTTP_{name.upper()}": value for name, value in headers.items()})
    setup_testing_defaults(environ)
    environ["wsgi.input"] = io.BytesIO()
    answered: dict = {}

    def start_response(status: str, response_headers: list) -> None:
        answered.update(status=status, headers=dict(response_headers))

    body = b"".join(worker_metrics_app(environ, start_response))
    return answered["status"], answered["headers"], body


def test_the_port_answers_the_webs_metrics_with_its_token_rule(settings):
    settings.METRICS_TOKEN = TOKEN
    status, headers, body = _get("/metrics")
    assert status == "200 OK"
    assert headers["Content-Type"].startswith("text/plain")
    assert b"authros_records_anchored_total" in body  # the counts
    assert b"authros_metrics_source_up" in body  # the state read when scraped, as the web's
    assert _get("/metrics", remote="203.0.113.7")[0].startswith("401")
    allowed = _get("/metrics", remote="203.0.113.7", authorization=f"Bearer {TOKEN}")
    assert allowed[0] == "200 OK"
    assert _get("/metrics", method="OPTIONS")[1]["Allow"] == "GET, HEAD, OPTIONS"
    assert _get("/metrics", method="HEAD")[2] == b""


@pytest.mark.parametrize("path", ["/", "/admin/", "/api/v1/records/", "/healthz", "/metrics/x"])
def test_nothing_else_is_served_on_the_port(path):
    status, _, body = _get(path)
    assert status == "404 Not Found"
    assert b"authros_" not in body


def test_the_worker_serves_it_once_ready_where_a_port_is_set(settings):
    settings.WORKER_METRICS_PORT = 0
    assert worker_metrics_serve() is None
    settings.WORKER_METRICS_PORT = free_port()
    server = worker_metrics_serve()
    assert server is not None
    try:
        # A client that connects and says nothing holds up no scrape.
        with socket.create_connection(("127.0.0.1", settings.WORKER_METRICS_PORT)):
            answer = requests.get(
                f"http://127.0.0.1:{settings.WORKER_METRICS_PORT}/metrics", timeout=30
            )
        assert answer.status_code == 200
        assert "authros_metrics_source_up" in answer.text
    finally:
        server.shutdown()
        server.server_close()


def test_a_port_taken_is_logged_and_the_worker_goes_on(settings):
    with (
        socket.create_server(("127.0.0.1", 0)) as taken,
        logged_by("portal.worker_metrics") as logs,
    ):
        settings.WORKER_METRICS_PORT = taken.getsockname()[1]
        assert worker_metrics_serve() is None
    assert any("not served" in record.getMessage() for record in logs)


def test_workers_import_it_once_djangos_apps_are_loaded():
    assert "portal.worker_metrics" in app.conf.imports
