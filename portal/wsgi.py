"""WSGI entry point (gunicorn portal.wsgi)."""

import os

from django.core.wsgi import get_wsgi_application
from django.urls import get_resolver

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

application = get_wsgi_application()

# Import every view now, while the worker boots, not on the first requests it serves: a cold
# worker (after a start or a max-requests recycle) would otherwise spend its first seconds
# importing the URLconf, DRF and the apps on the clock of the requests waiting for it.
get_resolver().url_patterns  # noqa: B018
