"""The root of every app's refusals: a machine-readable `code` and the HTTP status it maps
to (core/api_errors.py answers with both), so no layer below the entry points knows HTTP."""


class DomainError(Exception):
    code = "error"
    http_status = 400
    # Seconds a client should wait before asking again; None when asking again will not help.
    retry_after: int | None = None
