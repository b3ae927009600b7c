"""Log lines of every process: one JSON object per line, or a readable line for a terminal.

Every line carries what a person reading the logs of many processes needs to join them: the
request id (the `X-Request-Id` of the web request, carried into the Celery tasks it queued),
and the owner or robot the request acted for, where known. They live in context variables
set by the web middleware and the Celery signals (portal/middleware.py, portal/celery.py), so
no call site passes them.

No line may carry a secret, a key or content. What the portal logs is written not to; as a
second guard, anything shaped like a credential in a message (an `Authorization` value, a
`Token`/`Bearer` key, a `password=`/`sm4_key=` value, 32 hex digits: an SM4 key) is replaced by
`[redacted]` before the line is written; and Celery's "task succeeded" line goes without the
task's return value unless it is a number (a view's check returns the record's envelope).
"""

from __future__ import annotations

import json
import logging
import re
import uuid
from contextvars import ContextVar, Token
from datetime import UTC, datetime
from typing import Any

# At most this long, of these characters: an incoming X-Request-Id that is anything else is
# replaced (it is echoed in an answer header and written in every log line).
_REQUEST_ID = re.compile(r"[A-Za-z0-9._:-]{1,128}")
_SECRET_SHAPES = re.compile(
    # an Authorization value: "Token <key>", "Bearer <key>", "Basic <base64>"
    r"\b(?:Token|Bearer|Basic)\s+[A-Za-z0-9._~+/=-]{8,}"
    # a named secret: password=..., "sm4_key_hex": "...", authorization: ...
    r"|(?i:(?:authorization|password|secret|sm4_key(?:_hex)?|private_key|api_key|token)"
    r"[\"']?\s*[:=]\s*[\"']?(?:(?:Token|Bearer|Basic)\s+)?[^\s\"',;&}]+)"
    # 32 hex digits alone: an SM4 key, the master key
    r"|\b[0-9a-fA-F]{32}\b"
)
REDACTED = "[redacted]"
# A task's return value logged as it is: a number or a constant (how many records a run
# anchored); anything else may carry content.
_PLAIN_VALUE = re.compile(r"-?\d+(\.\d+)?|None|True|False")

_context: ContextVar[dict[str, Any] | None] = ContextVar("authros_log_context", default=None)


def request_id_new() -> str:
    return str(uuid.uuid4())


def request_id_accepted(value: str | None) -> str:
    """An incoming request id if it is a sane one (a proxy's or a client's), else a new one."""
    if value and _REQUEST_ID.fullmatch(value):
        return value
    return request_id_new()


def log_context_set(**fields: Any) -> Token:
    """Start a context (a request, a task): these fields on every line logged inside it."""
    return _context.set({key: value for key, value in fields.items() if value is not None})


def log_context_add(**fields: Any) -> None:
    """Add fields to the current context (the owner once the request is authenticated)."""
    current = _context.get()
    if current is not None:
        current.update({key: value for key, value in fields.items() if value is not None})


def log_context_reset(token: Token) -> None:
    _context.reset(token)


def log_context() -> dict[str, Any]:
    return dict(_context.get() or {})


def current_request_id() -> str | None:
    return (_context.get() or {}).get("request_id")


def redacted(text: str) -> str:
    return _SECRET_SHAPES.sub(REDACTED, text)


class ContextFilter(logging.Filter):
    """Puts the context's fields on each record (record.context) for the formatters, and keeps
    a task's return value out of Celery's "succeeded" line."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.context = log_context()
        if isinstance(record.args, dict) and "return_value" in record.args:
            shown = str(record.args["return_value"])
            if not _PLAIN_VALUE.fullmatch(shown):
                record.args = {**record.args, "return_value": "(not logged)"}
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message, the context's fields (request
    id, owner, robot, task), the process, and the traceback of an exception."""

    def format(self, record: logging.LogRecord) -> str:
        line: dict[str, Any] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname,
            "logger": record.name,
            "message": redacted(record.getMessage()),
            **(getattr(record, "context", None) or log_context()),
            "process": record.process,
        }
        if record.exc_info:
            line["exception"] = redacted(self.formatException(record.exc_info))
        return json.dumps(line, ensure_ascii=False, default=str)


class ConsoleFormatter(logging.Formatter):
    """A readable line for a terminal (`LOG_FORMAT=console`, make run's default), with the
    request id where there is one."""

    def __init__(self) -> None:
        super().__init__(
            "%(asctime)s %(levelname)s %(name)s %(process)d%(context_text)s %(message)s"
        )

    def format(self, record: logging.LogRecord) -> str:
        context = getattr(record, "context", None) or log_context()
        record.context_text = "".join(f" {key}={value}" for key, value in context.items())
        record.msg = redacted(record.getMessage())
        record.args = None
        return super().format(record)


def logging_config(*, log_format: str, level: str) -> dict[str, Any]:
    """Django's LOGGING for `log_format` json or console (settings.LOG_FORMAT)."""
    if log_format not in ("json", "console"):
        raise ValueError(f"LOG_FORMAT must be json or console, not {log_format!r}")
    return {
        "version": 1,
        "disable_existing_loggers": False,
        "filters": {"context": {"()": ContextFilter}},
        "formatters": {
            "json": {"()": JsonFormatter},
            "console": {"()": ConsoleFormatter},
        },
        "handlers": {
            "default": {
                "class": "logging.StreamHandler",
                "formatter": log_format,
                "filters": ["context"],
            }
        },
        "root": {"handlers": ["default"], "level": level},
        "loggers": {
            "web3": {"level": "WARNING"},
            "urllib3": {"level": "WARNING"},
        },
    }
