"""The endpoint browsers report Content-Security-Policy violations to (portal.csp).

Browsers send what they blocked both as `report-uri` (one JSON object,
`application/csp-report`) and as `report-to` (the Reporting API: a list,
`application/reports+json`). A report is anybody's input: it is read up to
CSP_REPORT_MAX_BYTES, at most CSP_REPORTS_PER_REQUEST of a list, each field cut to
CSP_REPORT_FIELD_CHARS printable characters with query strings and fragments dropped (they
could carry a token), logged at WARNING, and counted per client address (the "csp_report" API
rate). Junk is a 400 or 413, never a 500.
"""

import json
import logging
import unicodedata
from collections.abc import Mapping
from typing import Any

from rest_framework import exceptions, status
from rest_framework.parsers import BaseParser
from rest_framework.permissions import AllowAny
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import AnonRateThrottle

logger = logging.getLogger(__name__)

CSP_REPORT_MAX_BYTES = 16 * 1024
CSP_REPORTS_PER_REQUEST = 10
CSP_REPORT_FIELD_CHARS = 200

# What is logged of a report, by its name in `report-uri` bodies and in Reporting API bodies.
_FIELDS = {
    "document": ("document-uri", "documentURL"),
    "directive": ("effective-directive", "effectiveDirective", "violated-directive"),
    "blocked": ("blocked-uri", "blockedURL"),
    "source": ("source-file", "sourceFile"),
    "line": ("line-number", "lineNumber"),
    "sample": ("script-sample", "sample"),
}
_URI_FIELDS = ("document", "blocked", "source")


def csp_reports_read(body: object) -> list[dict[str, str]]:
    """The violations a report body holds, sanitised: a `report-uri` object
    ({"csp-report": {...}}) or a Reporting API list ([{"type": "csp-violation", "body":
    {...}}, ...]), at most CSP_REPORTS_PER_REQUEST. Raises ValueError for anything else."""
    if isinstance(body, Mapping) and isinstance(body.get("csp-report"), Mapping):
        raw = [body["csp-report"]]
    elif isinstance(body, list) and body:
        raw = [
            item["body"]
            for item in body[:CSP_REPORTS_PER_REQUEST]
            if isinstance(item, Mapping)
            and item.get("type") == "csp-violation"
            and isinstance(item.get("body"), Mapping)
        ]
    else:
        raw = []
    if not raw:
        raise ValueError("no Content-Security-Policy violation report in the body")
    return [_violation(report) for report in raw]


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
    """Both report bodies browsers send, and plain JSON; bounded before it is read whole."""

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

    def post(self, request: Request) -> Response:
        if request.META.get("CONTENT_LENGTH", "0").isdigit() and (
            int(request.META.get("CONTENT_LENGTH", "0")) > CSP_REPORT_MAX_BYTES
        ):
            raise _TooLarge()
        try:
            violations = csp_reports_read(request.data)
        except ValueError as exc:
            raise exceptions.ParseError(str(exc)) from None
        for violation in violations:
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
