"""Chain work waiting in the apps, counted for the admin's chain status page.

The apps own those rows (records, owners, keys, grants), and this layer imports none of them:
each app registers a counter here when Django starts (its AppConfig.ready).
"""

from collections.abc import Callable

BacklogCounter = Callable[[], dict[str, int]]

_counters: list[BacklogCounter] = []


def backlog_counter_register(counter: BacklogCounter) -> None:
    if counter not in _counters:
        _counters.append(counter)


def backlog_counts() -> dict[str, int]:
    """Every registered counter's numbers, in one mapping (`records`, `registrations`, ...)."""
    counts: dict[str, int] = {}
    for counter in _counters:
        counts.update(counter())
    return counts
