"""WSGI entry point (granian portal.wsgi:application --interface wsgi)."""

import gc
import logging
import os

from django.core.wsgi import get_wsgi_application
from django.db import connections
from django.urls import get_resolver

from portal.celery import app
from portal.middleware import service_problems

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

application = get_wsgi_application()

logger = logging.getLogger(__name__)


def warm_up() -> None:
    """What every worker would otherwise do on the clock of its first requests, done while it
    boots (after a start or a max-requests recycle): import every view, run the service checks
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
