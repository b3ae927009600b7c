"""What a logger logs while a test runs, kept apart from pytest's caplog."""

import logging
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def logged_by(name: str) -> Iterator[list[logging.LogRecord]]:
    """What the logger `name` logs meanwhile (pytest's caplog loses its handler when the first
    task run inline sets Django's logging up again)."""
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append
    logger = logging.getLogger(name)
    logger.addHandler(handler)
    try:
        yield records
    finally:
        logger.removeHandler(handler)
