"""What wraps every request, first of all the middleware: the probes, and each request's id,
log context, access line and metrics.

The probes (/healthz, /readyz, /metrics: portal/probes.py) are answered here, before any other
middleware: a load balancer's probe names the host by its address, which ALLOWED_HOSTS would
refuse; it must not be redirected to https, create a session, or wait for the service checks
(/readyz reports what fails; /healthz answers without the database). They are neither
rate-limited (no API throttle runs) nor logged nor counted per request, so that a monitor
asking every few seconds does not fill the logs.

Every other request gets an id (a sane incoming `X-Request-Id`, else a new one), answered in
`X-Request-Id`, on every log line of the request with the user, owner and robot once known
(core/logging.py), and carried into the Celery tasks the request queues (portal/celery.py);
its client's connection is known while it is served (core/client.py).
When the answer is out, one access line is logged and the request is counted
(portal/metrics.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from django.http import HttpRequest, HttpResponse

from core.client import client_connection_reset, client_connection_set
from core.logging import (
    REDACTED,
    log_context_add,
    log_context_reset,
    log_context_set,
    request_id_accepted,
)
from portal.metrics import request_observed
from portal.probes import PROBES

access_logger = logging.getLogger("portal.access")
REQUEST_ID_HEADER = "X-Request-Id"


class RequestContextMiddleware:
    """The probes, and every other request's id, log context, access line and metrics."""

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        request_id = request_id_accepted(request.headers.get(REQUEST_ID_HEADER))
        request.request_id = request_id  # type: ignore[attr-defined]
        context = log_context_set(request_id=request_id)
        client = client_connection_set(request.META.get("gunicorn.socket"))
        try:
            probe = PROBES.get(request.path)
            if probe is not None:
                response = probe(request)
                response[REQUEST_ID_HEADER] = request_id
                # Django would log a 503 from /readyz at ERROR, once per probe.
                response._has_been_logged = True  # type: ignore[attr-defined]
                return response
            started = time.perf_counter()
            response = self.get_response(request)
            response[REQUEST_ID_HEADER] = request_id
            seconds = time.perf_counter() - started
            request_observed(request, response, seconds)
            access_logger.info(
                "%s %s %s %.1f ms",
                request.method,
                _path_shown(request),
                response.status_code,
                seconds * 1000,
            )
            return response
        finally:
            client_connection_reset(client)
            log_context_reset(context)

    def process_view(self, request: HttpRequest, *args: Any) -> None:
        """The signed-in user on the rest of the request's lines (an API token's owner and
        robot are added where the token is checked: accounts/authentication.py)."""
        user = getattr(request, "user", None)
        if user is not None and user.is_authenticated:
            log_context_add(user=user.pk)


def _path_shown(request: HttpRequest) -> str:
    """The path for the access line, a token in it (an e-mail verification link's) redacted;
    never the query string."""
    path = request.path
    match = getattr(request, "resolver_match", None)
    for name, value in match.kwargs.items() if match is not None else ():
        if "token" in name and value:
            path = path.replace(str(value), REDACTED)
    return path
