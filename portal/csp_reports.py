"""The endpoint browsers report Content-Security-Policy violations to (portal.csp).

Browsers POST what they blocked, one violation a request, as `report-uri` asks (a JSON object
`{"csp-report": {...}}`, `application/csp-report`). A report is anybody's input: it is read up
to CSP_REPORT_MAX_BYTES, each field cut to CSP_REPORT_FIELD_CHARS printable characters with
query strings and fragments dropped (they could carry a token), logged at WARNING, and counted
per client address (the "csp_report" API rate). Junk is a 400 or 413, never a 500.
"""

import json
import logging
import unicodedata
from collections.abc import Mapping
from typing import Any

from drf_spectacular.utils import extend_schema
from rest_framework import exceptions, status
from rest_framework.parsers import BaseParser
from rest_framework.permissions import AllowAny
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import AnonRateThrottle

logger = logging.getLogger(__name__)

CSP_REPORT_MAX_BYTES = 16 * 1024
CSP_REPORT_FIELD_CHARS = 200

# What is logged of a report: its field, or the first of its fields that the report has.
_FIELDS = {
    "document": ("document-uri",),
    "directive": ("effective-directive", "violated-directive"),
    "blocked": ("blocked-uri",),
    "source": ("source-file",),
    "line": ("line-number",),
    "sample": ("script-sample",),
}
_URI_FIELDS = ("document", "blocked", "source")


def csp_report_read(body: object) -> dict[str, str]:
    """The violation a `report-uri` body ({"csp-report": {...}}) holds, sanitised. Raises
    ValueError for anything else."""
    if not (isinstance(body, Mapping) and isinstance(body.get("csp-report"), Mapping)):
        raise ValueError("no Content-Security-Policy violation report in the body")
    return _violation(body["csp-report"])


def _violation(report: Mapping[str, Any]) -> dict[str, str]:
    found = {}
    for name, keys in _FIELDS.items():
        value = next((report[key] for key in keys if key in report), "")
        text = str(value) if isinstance(value, str | int | float) else ""
        if name in _URI_FIELDS:
            text = text.split("?", 1)[0].split("#", 1)[0]
        found[name] = _printable(text)[:CSP_REPORT_FIELD_CHARS]
    return found


def _printable(text: str) -> str:
    # Control, format (U+202E) and separator characters could forge or hide log lines.
    return "".join(
        char if unicodedata.category(char)[0] not in "CZ" or char == " " else "_"
        for char in text[: CSP_REPORT_FIELD_CHARS * 2]
    )


class CspReportParser(BaseParser):
    """A JSON body whatever its content type (browsers say application/csp-report), refused
    past CSP_REPORT_MAX_BYTES before it is read whole."""

    media_type = "*/*"

    def parse(
        self,
        stream: Any,
        media_type: str | None = None,
        parser_context: Mapping[str, Any] | None = None,
    ) -> object:
        data = stream.read(CSP_REPORT_MAX_BYTES + 1) if stream is not None else b""
        if len(data) > CSP_REPORT_MAX_BYTES:
            raise _TooLarge()
        try:
            return json.loads(data)
        except (ValueError, RecursionError) as exc:
            raise exceptions.ParseError("a report is a JSON object or list") from exc


class _TooLarge(exceptions.APIException):
    status_code = status.HTTP_413_REQUEST_ENTITY_TOO_LARGE
    default_detail = f"a report is at most {CSP_REPORT_MAX_BYTES} bytes"
    default_code = "request_too_large"


class CspReportThrottle(AnonRateThrottle):
    """Reports per client address (the "csp_report" rate), apart from the API's own."""

    scope = "csp_report"

    def get_cache_key(self, request: Request, view: APIView) -> str | None:
        return self.cache_key_for(self.get_ident(request))


class CspReportView(APIView):
    """POST a Content-Security-Policy violation report: 204 once logged."""

    authentication_classes: list = []
    permission_classes = [AllowAny]
    parser_classes = [CspReportParser]
    throttle_classes = [CspReportThrottle]

    # Browsers' endpoint, not the agents' API: left out of its schema.
    @extend_schema(exclude=True)
    def post(self, request: Request) -> Response:
        if request.META.get("CONTENT_LENGTH", "0").isdigit() and (
            int(request.META.get("CONTENT_LENGTH", "0")) > CSP_REPORT_MAX_BYTES
        ):
            raise _TooLarge()
        try:
            violation = csp_report_read(request.data)
        except ValueError as exc:
            raise exceptions.ParseError(str(exc)) from None
        logger.warning(
            "Content-Security-Policy violation: %s blocked %s on %s (%s:%s) %s",
            violation["directive"] or "?",
            violation["blocked"] or "?",
            violation["document"] or "?",
            violation["source"] or "?",
            violation["line"] or "?",
            violation["sample"],
        )
        return Response(status=status.HTTP_204_NO_CONTENT)
