"""What the portal counts for Prometheus (core/metrics.py holds the metrics themselves and the
exposition; portal/scrape.py what is read when scraped).

Counted at the entry points, so the apps carry no metric code: every web request by the
middleware (`request_observed`: uploads and integrity-checked views by result, with their
latency), every Celery task by a signal (`task_observed`: verdicts by outcome, records
anchored, exports and alert deliveries by status), every mined transaction by the chain client.
Imported by the Celery app before Django's apps are loaded: no models here.
"""

from __future__ import annotations

import re
from typing import Any

from django.http import HttpRequest, HttpResponse

from core.metrics import (
    ALERT_DELIVERIES,
    ENVELOPES,
    EXPORTS,
    HTTP_REQUESTS,
    RECORDS_ANCHORED,
    TASKS,
    UPLOAD_SECONDS,
    UPLOADS,
    VIEW_SECONDS,
    VIEWS,
)

# The routes (URL patterns) of the requests counted as uploads and as integrity-checked views.
UPLOAD_ROUTES = frozenset({("POST", "api/v1/records/")})
VIEW_ROUTES = frozenset(
    {
        ("GET", "api/v1/records/<str:record_id>/content/"),
        ("GET", "records/<uuid:record_id>/"),
        ("GET", "records/<uuid:record_id>/raw.json"),
    }
)

# A label's values are bounded whatever a client sends: every series lives in each web
# process's file and in every scrape until the process restarts. A method outside these
# (HTTP lets a client make any up) is counted as "other"; so is a status outside 100-599, and a
# result that is not an error code of the API's shape.
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "TRACE"})
OTHER = "other"
_ERROR_CODE = re.compile(r"[a-z][a-z0-9_]{0,47}")

ANCHOR_TASK = "sharing.tasks.records_anchor"
EXPORT_TASK = "sharing.tasks.export_run"
ALERT_DELIVERY_TASK = "alerts.tasks.alert_deliver"


# --- events --------------------------------------------------------------------------------------


def request_route(request: HttpRequest) -> str:
    """The URL pattern the request matched (few values, unlike paths), or "unmatched"."""
    match = getattr(request, "resolver_match", None)
    return match.route if match is not None else "unmatched"


def request_method(request: HttpRequest) -> str:
    """The request's method as a label: one of HTTP_METHODS, or "other"."""
    method = request.method or ""
    return method if method in HTTP_METHODS else OTHER


def response_status(response: HttpResponse) -> str:
    """The answer's status as a label: its code when a valid HTTP status, else "other"."""
    code = response.status_code
    return str(code) if isinstance(code, int) and 100 <= code <= 599 else OTHER


def request_observed(request: HttpRequest, response: HttpResponse, seconds: float) -> None:
    route = request_route(request)
    method = request_method(request)
    HTTP_REQUESTS.labels(route, method, response_status(response)).inc()
    if (method, route) in UPLOAD_ROUTES:
        result = _result(response, ok="stored")
        UPLOADS.labels(result).inc()
        UPLOAD_SECONDS.labels(result).observe(seconds)
        ENVELOPES.labels(result).inc(_envelopes_in(response))
    elif (method, route) in VIEW_ROUTES:
        result = _result(response, ok="verified")
        VIEWS.labels(result).inc()
        VIEW_SECONDS.labels(result).observe(seconds)


def _result(response: HttpResponse, *, ok: str) -> str:
    """`ok` for a success, else the API's error code (`replayed_sequence`, ...) or the status."""
    if response.status_code < 400:
        return ok
    data = getattr(response, "data", None)
    code = data.get("error") if isinstance(data, dict) else None
    if isinstance(code, str) and _ERROR_CODE.fullmatch(code):
        return code
    return response_status(response)


def _envelopes_in(response: HttpResponse) -> int:
    """Envelopes the upload carried: those stored, or those its refused request held."""
    if response.status_code < 400:
        data = getattr(response, "data", None)
        return len(data) if isinstance(data, list) else 1
    request = (getattr(response, "renderer_context", None) or {}).get("request")
    try:
        body = request.data if request is not None else None
    except Exception:  # an unreadable body was the refusal itself
        body = None
    envelopes = body.get("envelopes") if isinstance(body, dict) else None
    return len(envelopes) if isinstance(envelopes, list) and envelopes else 1


def task_observed(name: str, state: str, retval: Any) -> None:
    """A finished Celery task: its state, and what its answer says about the domain."""
    TASKS.labels(name, state).inc()
    if state != "SUCCESS":
        return
    # Verdicts are counted where they are written (sharing/verification/check.py): a series'
    # task answers only counts, and a single record's check may not be a task at all.
    if name == ANCHOR_TASK and isinstance(retval, int) and retval > 0:
        RECORDS_ANCHORED.inc(retval)
    elif name == EXPORT_TASK and isinstance(retval, str):
        EXPORTS.labels(retval).inc()
    elif name == ALERT_DELIVERY_TASK:
        ALERT_DELIVERIES.labels(retval if isinstance(retval, str) else "skipped").inc()
