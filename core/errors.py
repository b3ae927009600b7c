"""The root of every app's refusals: a machine-readable `code`, the HTTP status it maps to and,
where asking again later helps, `retry_after` (for a Retry-After header).

Each app's errors.py declares that status beside the error, as plain data: the one map from
domain errors to HTTP. Services and selectors only raise these; the entry points turn them into
answers (core/api_errors.py for the API, the views for pages), and only they and what serves
them (accounts/decorators.py, accounts/authentication.py, core/api_*.py) import Django's or
DRF's HTTP modules."""


class DomainError(Exception):
    code = "error"
    http_status = 400
    # Seconds a client should wait before asking again; None when asking again will not help.
    retry_after: int | None = None
