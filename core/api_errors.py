"""The one mapping from errors to HTTP answers of the REST API: `{"error", "detail"}`.

`error` is a stable machine-readable code, `detail` one line of text for people; a request
refused by validation also carries `fields`, the problems per input field.
"""

import logging
from collections.abc import Mapping, Sequence
from typing import Any

from django.core.exceptions import PermissionDenied, RequestDataTooBig
from django.http import Http404, HttpRequest, JsonResponse
from django.views.decorators.csrf import csrf_exempt
from drf_spectacular.utils import OpenApiResponse
from rest_framework import exceptions, serializers, status
from rest_framework.response import Response
from rest_framework.views import exception_handler as drf_exception_handler
from rest_framework.views import set_rollback

from core.errors import DomainError

logger = logging.getLogger(__name__)

_DRF_CODES = {
    exceptions.ParseError: "malformed_request",
    exceptions.AuthenticationFailed: "not_authenticated",
    exceptions.NotAuthenticated: "not_authenticated",
    exceptions.PermissionDenied: "permission_denied",
    exceptions.NotFound: "not_found",
    exceptions.MethodNotAllowed: "method_not_allowed",
    exceptions.NotAcceptable: "not_acceptable",
    exceptions.UnsupportedMediaType: "unsupported_media_type",
    exceptions.Throttled: "rate_limited",
    exceptions.ValidationError: "invalid_request",
}


def exception_handler(exc: Exception, context: dict[str, Any]) -> Response:
    if isinstance(exc, DomainError):
        response = _answer(exc.code, str(exc), exc.http_status)
        if exc.retry_after is not None:
            response["Retry-After"] = str(exc.retry_after)
        return response
    if isinstance(exc, RecursionError):
        return _answer("malformed_request", "the request is nested too deeply", 400)
    if isinstance(exc, RequestDataTooBig):
        return _answer(
            "request_too_large",
            "the request body is larger than the portal accepts: send fewer envelopes at once",
            status.HTTP_413_REQUEST_ENTITY_TOO_LARGE,
        )
    if isinstance(exc, Http404):
        exc = exceptions.NotFound()
    elif isinstance(exc, PermissionDenied):
        exc = exceptions.PermissionDenied()
    response = drf_exception_handler(exc, context)
    if response is None:
        # A bug, not the client's doing: logged with its traceback, answered in the API's shape.
        logger.error("unhandled error in %s", _view_name(context), exc_info=exc)
        return _answer("server_error", "the portal failed to answer; this was logged", 500)
    code = next((c for cls, c in _DRF_CODES.items() if isinstance(exc, cls)), "error")
    if isinstance(exc, exceptions.ValidationError):
        response.data = {
            "error": code,
            "detail": validation_text(exc.detail),
            "fields": _field_errors(exc.detail),
        }
    else:
        response.data = {"error": code, "detail": str(getattr(exc, "detail", exc))}
    return response


def validation_text(detail: Any, path: str = "") -> str:
    """One line from DRF's nested validation detail: `envelopes[2]: not valid base64`."""
    if isinstance(detail, Mapping):
        parts = []
        for name, value in detail.items():
            if name == "non_field_errors":
                where = path
            elif isinstance(name, int):
                where = f"{path}[{name}]"
            else:
                where = f"{path}.{name}" if path else str(name)
            parts.append(validation_text(value, where))
        return "; ".join(part for part in parts if part)
    if isinstance(detail, Sequence) and not isinstance(detail, str):
        return "; ".join(validation_text(item, path) for item in detail)
    return f"{path}: {detail}" if path else str(detail)


def _field_errors(detail: Any) -> dict[str, Any]:
    if isinstance(detail, Mapping):
        return {str(name): value for name, value in detail.items()}
    return {"non_field_errors": detail if isinstance(detail, list) else [detail]}


def _answer(code: str, detail: str, http_status: int) -> Response:
    set_rollback()
    return Response({"error": code, "detail": detail}, status=http_status)


def _view_name(context: dict[str, Any]) -> str:
    view = context.get("view")
    return type(view).__name__ if view is not None else "an API view"


# --- the error shape in the OpenAPI schema -------------------------------------------------


class ErrorSerializer(serializers.Serializer):
    error = serializers.CharField(help_text="machine-readable code, e.g. `replayed_sequence`")
    detail = serializers.CharField(help_text="what went wrong and what to do, for people")
    fields = serializers.DictField(
        required=False, help_text="validation problems per input field (400 invalid_request)"
    )


_ERROR_DESCRIPTIONS = {
    400: "invalid input: `invalid_request`, `malformed_request`, `invalid_envelope`, ...",
    401: "`not_authenticated`: no credentials, or an unknown or revoked token",
    403: "refused: `permission_denied`, `access_denied`, `header_mismatch`, ...",
    404: "`not_found`",
    409: "conflicts with the current state",
    410: "`record_deleted`: the record was deleted; its metadata and proof stay",
    413: "`request_too_large`: the request body, or `envelope_too_large`: one envelope",
    415: "`unsupported_media_type`: send `application/json`",
    429: "`rate_limited`: wait for `Retry-After` seconds",
    503: "`verification_unavailable`: the integrity check could not run now; retry later",
}


def error_responses(*codes: int, **descriptions: str) -> dict[int, OpenApiResponse]:
    """Schema entries for the error answers an operation can give (429 always).

    `descriptions` override the generic text per status, keyed `e403="..."`.
    """
    result = {}
    for code in sorted({*codes, 429}):
        text = descriptions.get(f"e{code}", _ERROR_DESCRIPTIONS[code])
        result[code] = OpenApiResponse(ErrorSerializer, description=text)
    return result


@csrf_exempt  # it changes nothing: a POST with a session cookie gets the JSON 404 too
def api_not_found(request: HttpRequest) -> JsonResponse:
    """Any path under `/api/` that is no endpoint: a JSON 404, not the HTML page."""
    hint = "" if request.path.endswith("/") else " (API paths end with a slash)"
    return JsonResponse(
        {"error": "not_found", "detail": f"no API endpoint at {request.path}{hint}"}, status=404
    )
