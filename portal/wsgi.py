"""WSGI entry point (gunicorn portal.wsgi:application, stack/processes.py web_server)."""

import gc
import logging
import os
from collections.abc import Callable, Iterable

from django.core.wsgi import get_wsgi_application
from django.db import connections
from django.urls import get_resolver

from portal.celery import app
from portal.middleware import service_problems

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

# The keys a WSGI server sets for each request (PEP 3333, CGI): kept whatever else is dropped.
_REQUEST_KEYS = frozenset(
    {
        "CONTENT_LENGTH",
        "CONTENT_TYPE",
        "GATEWAY_INTERFACE",
        "PATH_INFO",
        "QUERY_STRING",
        "REMOTE_ADDR",
        "REMOTE_HOST",
        "REMOTE_PORT",
        "REQUEST_METHOD",
        "SCRIPT_NAME",
        "SERVER_NAME",
        "SERVER_PORT",
        "SERVER_PROTOCOL",
        "SERVER_SOFTWARE",
    }
)


def without_process_environment(
    app: Callable[[dict, Callable], Iterable[bytes]], process_environment: Iterable[str]
) -> Callable[[dict, Callable], Iterable[bytes]]:
    """app, given each request's environ without the variables of this process's environment.

    A server may start every request's environ from a copy of the process's environment (CGI
    does, granian did; gunicorn does not, and this keeps it so whatever serves the portal),
    secrets included (DJANGO_SECRET_KEY, AUTHROS_MASTER_KEY, database and Redis URLs with their
    passwords). Django keeps the environ as request.META, which error reports print and any
    code can read: what a request carries is what the request and the server set. A process
    variable named like a header (HTTP_PROXY) goes too, as the httpoxy advisories say.
    """
    dropped = tuple(sorted(set(process_environment) - _REQUEST_KEYS))

    def application(environ: dict, start_response: Callable) -> Iterable[bytes]:
        for key in dropped:
            environ.pop(key, None)
        return app(environ, start_response)

    return application


application = get_wsgi_application()

logger = logging.getLogger(__name__)


def warm_up() -> None:
    """What every worker would otherwise do on the clock of its first requests, done while it
    boots (after a start or a recycle): import every view, run the service checks
    (database, master key, the chain's operator: portal/middleware.py), and set up the Celery
    result backend and broker producers that uploads and views use. A part that cannot be
    reached now is only logged: the requests meet it again, as without this."""
    get_resolver().url_patterns  # noqa: B018
    try:
        service_problems()
        app.loader.import_default_modules()
        app.backend  # noqa: B018
        app.producer_pool  # noqa: B018
    except Exception as exc:  # the first requests meet it again and report it
        logger.warning("worker warm-up incomplete: %s", exc)
    finally:
        connections.close_all()  # the boot thread serves nothing; request threads have theirs
    # What the boot made (modules, the URL resolver, clients) lives as long as the worker: out
    # of the collector's sight from here. A full collection walked all of it while requests
    # waited (one took 130 ms of a worker's CPU, the GIL held, in the 700-upload burst); now
    # it walks what requests made.
    gc.collect()
    gc.freeze()


warm_up()
# The environment as the server copies it: after the settings read `.env` into it and the
# warm-up's imports added theirs.
application = without_process_environment(application, os.environ)
