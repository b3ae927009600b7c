"""The AuthROS portal project: settings, URLs, the Celery app."""

import sys

import eth_account  # noqa: F401  (imports py_ecc, which raises the recursion limit)

from portal.celery import app as celery_app

# py_ecc sets the recursion limit to 100000; with that, parsing deeply nested JSON from a
# client overflows the C stack and kills the process instead of raising RecursionError.
SAFE_RECURSION_LIMIT = 3000
sys.setrecursionlimit(min(sys.getrecursionlimit(), SAFE_RECURSION_LIMIT))

__all__ = ["celery_app"]
