"""What load balancers, orchestrators and monitoring ask: /healthz, /readyz, /metrics.

They are answered by the first middleware (portal/request_context.py), past no other: no host
check, no session, no rate limit, no access line. /healthz answers as soon as the process
does, needing nothing else (not even the database).
/readyz says whether this process can serve now (portal/health.py). /metrics is the
Prometheus exposition (core/metrics.py): free to read from this host, with the bearer token
METRICS_TOKEN from anywhere else (docs/operations.md).

Each answers GET, HEAD (the same status and headers, no body) and OPTIONS (204 with Allow, as
HAProxy's `option httpchk` asks by default); any other method is 405 with Allow.
"""

from __future__ import annotations

import hmac
import ipaddress
from collections.abc import Callable
from functools import wraps

from django.conf import settings
from django.http import HttpRequest, HttpResponse, HttpResponseNotAllowed, JsonResponse
from django.views.decorators.cache import never_cache

from accounts.views import client_ip_address
from core.metrics import CONTENT_TYPE, metrics_text
from portal.health import readiness
from portal.scrape import state_collector

PROBE_METHODS = ("GET", "HEAD", "OPTIONS")


def probe(view: Callable[[HttpRequest], HttpResponse]) -> Callable[[HttpRequest], HttpResponse]:
    """The view for GET; HEAD gets its answer without the body, OPTIONS 204 with Allow."""

    @wraps(view)
    def answer(request: HttpRequest) -> HttpResponse:
        if request.method not in PROBE_METHODS:
            return HttpResponseNotAllowed(PROBE_METHODS)
        if request.method == "OPTIONS":
            response = HttpResponse(status=204)
            response["Allow"] = ", ".join(PROBE_METHODS)
            return response
        response = view(request)
        if request.method == "HEAD":
            length = len(response.content)
            response.content = b""
            response["Content-Length"] = str(length)
        return response

    return never_cache(answer)


@probe
def healthz(request: HttpRequest) -> HttpResponse:
    return JsonResponse({"status": "ok"})


@probe
def readyz(request: HttpRequest) -> HttpResponse:
    checks = readiness()
    ready = all(check.ok for check in checks)
    body = {
        "status": "ready" if ready else "unavailable",
        "checks": {check.part: {"ok": check.ok, "detail": check.detail} for check in checks},
        "failed": [check.part for check in checks if not check.ok],
    }
    return JsonResponse(body, status=200 if ready else 503)


@probe
def metrics(request: HttpRequest) -> HttpResponse:
    if not metrics_allowed(request):
        answer = JsonResponse(
            {
                "error": "metrics_token_required",
                "detail": "metrics are read from this host, or with the bearer token METRICS_TOKEN",
            },
            status=401,
        )
        answer["WWW-Authenticate"] = 'Bearer realm="metrics"'
        return answer
    return HttpResponse(metrics_text([state_collector]), content_type=CONTENT_TYPE)


def metrics_allowed(request: HttpRequest) -> bool:
    """From this host (the client address by the API's proxy rule, API_NUM_PROXIES), or with
    the right bearer token.

    With no proxy counted (API_NUM_PROXIES=0) a request that carries X-Forwarded-For came
    through a proxy that was not declared, which may well run on this host and connect from
    127.0.0.1 for every client: such a request needs the token too."""
    token = settings.METRICS_TOKEN
    given = request.headers.get("Authorization", "")
    if token and hmac.compare_digest(given.encode(), f"Bearer {token}".encode()):
        return True
    if not settings.REST_FRAMEWORK.get("NUM_PROXIES") and "HTTP_X_FORWARDED_FOR" in request.META:
        return False
    return _loopback(client_ip_address(request))


def _loopback(address: str | None) -> bool:
    try:
        return address is not None and ipaddress.ip_address(address.strip()).is_loopback
    except ValueError:
        return False


PROBES = {"/healthz": healthz, "/readyz": readyz, "/metrics": metrics}
