"""/metrics on a host that runs only Celery workers: the web's exposition, on a port of the
worker's own (WORKER_METRICS_PORT; 0, the default, serves none).

The worker's main process answers it, from a thread started once the worker is ready (its pool
forked): every pool process counts into the service's PROMETHEUS_MULTIPROC_DIR and the answer
adds up the files of every service of the host (core/metrics.py), so one worker service per host
serving it covers them all. The answer is the web's own view (portal/probes.py `metrics`):
free from this host, the bearer token METRICS_TOKEN from anywhere else, GET, HEAD and OPTIONS,
and the state read when scraped (portal/scrape.py). Nothing else is served on the port.

Loaded by the worker through Celery's `imports` (settings: CELERY_IMPORTS), once Django's apps
are: the view reads models, which portal/celery.py may not import.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading
from collections.abc import Callable, Iterable
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

from celery import signals
from django.conf import settings
from django.core.handlers.wsgi import WSGIRequest
from django.db import connections

from portal.probes import metrics

logger = logging.getLogger(__name__)

METRICS_PATH = "/metrics"
# Seconds a connection may take to send its request.
READ_TIMEOUT = 10.0
_NOT_FOUND = b'{"error": "not_found", "detail": "this port serves /metrics alone"}'


def worker_metrics_app(
    environ: dict[str, Any], start_response: Callable[..., Any]
) -> Iterable[bytes]:
    """The WSGI application of the port: /metrics through the web's view, else 404."""
    if environ.get("PATH_INFO") != METRICS_PATH:
        start_response("404 Not Found", [("Content-Type", "application/json")])
        return [_NOT_FOUND]
    try:
        response = metrics(WSGIRequest(environ))
    finally:
        connections.close_all()  # this thread's own: a scrape every 15 s needs none kept
    start_response(f"{response.status_code} {response.reason_phrase}", list(response.items()))
    return [response.content]


class _Server(ThreadingMixIn, WSGIServer):
    """A thread per connection: a client that connects and sends nothing (or a scrape waiting
    for a silent chain node) holds up no other scrape."""

    daemon_threads = True

    def handle_error(self, request: object, client_address: object) -> None:
        """One line, not socketserver's traceback on stderr (a client that timed out, ...)."""
        logger.warning(
            "worker metrics: a request from %s failed: %r", client_address, sys.exc_info()[1]
        )


class _ServerV6(_Server):
    address_family = socket.AF_INET6


class _QuietHandler(WSGIRequestHandler):
    """No line on stderr per scrape (the web logs none for its probes either); a connection
    that sends nothing is dropped after READ_TIMEOUT seconds."""

    timeout = READ_TIMEOUT

    def log_message(self, format: str, *args: object) -> None:
        pass


@signals.worker_ready.connect
def worker_metrics_serve(**kwargs: object) -> WSGIServer | None:
    """Serve /metrics on WORKER_METRICS_ADDRESS:WORKER_METRICS_PORT, if a port is set. A port
    that cannot be had is logged and the worker goes on working: its tasks matter more."""
    port = settings.WORKER_METRICS_PORT
    if not port:
        return None
    address = settings.WORKER_METRICS_ADDRESS
    try:
        server = make_server(
            address,
            port,
            worker_metrics_app,
            server_class=_ServerV6 if ":" in address else _Server,
            handler_class=_QuietHandler,
        )
    except OSError as exc:
        logger.error("worker metrics not served on %s:%s: %s", address, port, exc)
        return None
    # A pool process forked later (one replaced) drops its copy of the listening socket.
    os.register_at_fork(after_in_child=server.socket.close)
    threading.Thread(target=server.serve_forever, name="worker-metrics", daemon=True).start()
    logger.info("worker metrics at http://%s:%d%s", address, port, METRICS_PATH)
    return server
