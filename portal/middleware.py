"""Middleware of the portal: refusing to serve while its own configuration is wrong, and
the Content-Security-Policy of every answer (portal.csp says what it allows and why).

Refusing to serve while the portal's own configuration is wrong:

The checks registered under accounts.apps.SERVICE_CHECKS (the master key is the one the owner
keys were wrapped with, the operator key is the contract's admin) run on the first request of
each process. While they fail, every request but /static/ is answered 503 (JSON under /api/,
a page elsewhere), the operator message is logged at ERROR, and they run again every
SERVICE_CHECK_INTERVAL seconds, so that a fix is picked up without a restart. A chain that
does not answer is no refusal: the operator key is checked again later.
"""

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from django.conf import settings
from django.core.checks import run_checks
from django.db import DEFAULT_DB_ALIAS
from django.http import HttpRequest, HttpResponse, JsonResponse
from django.template.loader import render_to_string

from accounts.apps import SERVICE_CHECKS
from portal.csp import content_security_policy

logger = logging.getLogger(__name__)

MISCONFIGURED = "service_misconfigured"


@dataclass
class _Checked:
    problems: list[str] = field(default_factory=list)
    at: float | None = None  # time.monotonic() of the last check; None before the first
    settled: bool = False  # everything was checked and held: no need to check again


_checked = _Checked()
_lock = threading.Lock()


class ServiceChecksMiddleware:
    """503 for every request but /static/ while the service checks fail."""

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        if not request.path.startswith(settings.STATIC_URL):
            problems = service_problems()
            if problems:
                return _refusal(request, problems)
        return self.get_response(request)


def service_problems() -> list[str]:
    """Why the portal refuses to serve now; checked once per process, and again every
    SERVICE_CHECK_INTERVAL seconds while something fails or could not be checked."""
    if not _check_due():
        return _checked.problems
    with _lock:
        if _check_due():
            problems, unsure = _check_now()
            _checked.problems = problems
            _checked.at = time.monotonic()
            _checked.settled = not (problems or unsure)
        return _checked.problems


def service_checks_run() -> tuple[list[str], list[str]]:
    """Run the service checks now: the problems that refuse service, and what could not be
    checked (the chain did not answer), worth asking again."""
    messages = run_checks(tags=[SERVICE_CHECKS], databases=[DEFAULT_DB_ALIAS])
    problems = [message.msg for message in messages if message.is_serious()]
    unchecked = [message.msg for message in messages if not message.is_serious()]
    return problems, unchecked


def service_checks_forget() -> None:
    """Check again on the next request (tests change what the checks read)."""
    with _lock:
        _checked.problems = []
        _checked.at = None
        _checked.settled = False


def _check_due() -> bool:
    if _checked.settled:
        return False
    return _checked.at is None or (
        time.monotonic() - _checked.at >= settings.SERVICE_CHECK_INTERVAL
    )


def _check_now() -> tuple[list[str], bool]:
    try:
        problems, unchecked = service_checks_run()
    except Exception:
        # The database itself may be away: that is for the request to report, not this check.
        logger.warning("the portal's secrets could not be checked; trying again", exc_info=True)
        return [], True
    for problem in problems:
        logger.error("the portal refuses to serve until an operator fixes this: %s", problem)
    for note in unchecked:
        logger.warning("%s", note)
    return problems, bool(unchecked)


def _refusal(request: HttpRequest, problems: list[str]) -> HttpResponse:
    retry_after = str(max(1, math.ceil(settings.SERVICE_CHECK_INTERVAL)))
    if request.path.startswith("/api/"):
        detail = "the portal is misconfigured and serves nothing until an operator fixes it: "
        response: HttpResponse = JsonResponse(
            {"error": MISCONFIGURED, "detail": detail + "; ".join(problems)}, status=503
        )
    else:
        page = render_to_string("503_misconfigured.html", {"problems": problems})
        response = HttpResponse(page, status=503)
    response["Retry-After"] = retry_after
    response["Cache-Control"] = "no-store"
    # The operator message is logged once per check: Django would log each 503 at ERROR.
    response._has_been_logged = True  # type: ignore[attr-defined]
    return response


class ContentSecurityPolicyMiddleware:
    """The Content-Security-Policy (portal.csp) on every answer that sets none of its own."""

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response
        self.policy = content_security_policy()

    def __call__(self, request: HttpRequest) -> HttpResponse:
        response = self.get_response(request)
        response.headers.setdefault("Content-Security-Policy", self.policy)
        return response
