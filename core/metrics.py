"""The portal's Prometheus metrics: the counters and histograms every process updates, and the
text every web process answers /metrics with.

Counted where things happen (web requests, Celery tasks, chain transactions) by the official
prometheus-client. Several web processes and Celery worker processes count at once, so with
PROMETHEUS_MULTIPROC_DIR set (`make run` and the systemd units set it) each process writes its
counts to files there and a scrape adds up the files of every process of the host: the folder
of its own service and its siblings (`<root>/web`, `<root>/worker`, ...; each service empties
its own folder when it starts, `metrics_folder_reset`). Without it (a test, a shell) the
process's own counts are served.

What is state rather than an event (the anchoring backlog, queue depths, the chain's head) is
read when scraped, by collectors the caller hands to `metrics_text` (portal/scrape.py).
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

from prometheus_client import (
    REGISTRY,
    CollectorRegistry,
    Counter,
    Histogram,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
# No `*_created` series: the multiprocess files have none, so one process alone would differ.
disable_created_metrics()


def multiproc_folder() -> Path | None:
    value = os.environ.get(MULTIPROC_ENV, "")
    return Path(value) if value else None


# A metric without labels gets its file as it is defined, below: the folder must be there.
if (_folder := multiproc_folder()) is not None:
    _folder.mkdir(parents=True, exist_ok=True)

# Seconds: what a person waits for (an upload's answer, a record's integrity-checked view).
LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)

HTTP_REQUESTS = Counter(
    "authros_http_requests",
    "Web requests answered, by route (URL pattern), method and status code",
    ["route", "method", "status"],
)
UPLOADS = Counter(
    "authros_uploads",
    "Upload requests (POST /api/v1/records/) by result: stored, or the error code",
    ["result"],
)
ENVELOPES = Counter(
    "authros_envelopes",
    "Envelopes in upload requests by result: stored, or the error code of their request",
    ["result"],
)
UPLOAD_SECONDS = Histogram(
    "authros_upload_duration_seconds",
    "Time to answer an upload request",
    ["result"],
    buckets=LATENCY_BUCKETS,
)
VIEWS = Counter(
    "authros_views",
    "Integrity-checked views of records (API content, page, download) by result",
    ["result"],
)
VIEW_SECONDS = Histogram(
    "authros_view_duration_seconds",
    "Time to answer an integrity-checked view of a record",
    ["result"],
    buckets=LATENCY_BUCKETS,
)
VERDICTS = Counter(
    "authros_verdicts", "Integrity verdicts written by the workers, by outcome", ["outcome"]
)
RECORDS_ANCHORED = Counter("authros_records_anchored", "Records anchored on the chain")
CHAIN_TRANSACTIONS = Counter(
    "authros_chain_transactions",
    "Transactions mined, by contract function and result (ok, reverted)",
    ["function", "result"],
)
CHAIN_GAS = Counter(
    "authros_chain_gas_used", "Gas used by mined transactions, by contract function", ["function"]
)
TASKS = Counter(
    "authros_celery_tasks", "Celery tasks finished, by task and final state", ["task", "state"]
)
EXPORTS = Counter("authros_exports_finished", "Export runs finished, by status", ["status"])
ALERT_DELIVERIES = Counter(
    "authros_alert_deliveries", "Alert delivery attempts finished, by status", ["status"]
)


def chain_transaction_observed(function: str | None, *, ok: bool, gas_used: int) -> None:
    """A mined transaction: counted by the contract function it called, with its gas."""
    name = function or "other"
    CHAIN_TRANSACTIONS.labels(name, "ok" if ok else "reverted").inc()
    CHAIN_GAS.labels(name).inc(gas_used)


# --- the exposition -----------------------------------------------------------------------------


class CachedCollector:
    """`collect` answered from the last run of `read` for `seconds`: scrapes by several
    Prometheus servers (or a person's browser) cost one run of the queries behind it."""

    def __init__(self, read: Callable[[], Iterable], *, seconds: float) -> None:
        self.read = read
        self.seconds = seconds
        self._families: list = []
        self._at: float | None = None
        self._lock = threading.Lock()

    def collect(self) -> Iterator:
        with self._lock:
            now = time.monotonic()
            if self._at is None or now - self._at >= self.seconds:
                self._families = list(self.read())
                self._at = now
            families = self._families
        yield from families

    def forget(self) -> None:
        with self._lock:
            self._at = None


class _HostFiles:
    """Every process's counts from the files of every service of this host."""

    def __init__(self, root: Path) -> None:
        self.root = root

    def collect(self) -> Iterator:
        files = sorted(str(path) for path in self.root.glob("*/*.db") if _counts_begun(path))
        yield from MultiProcessCollector.merge(files, accumulate=True)


# A process's counts file holds at least its 8-byte header once the client has sized it.
_COUNTS_HEADER = 8


def _counts_begun(path: Path) -> bool:
    """Whether a process's counts file can be read: a process that is starting creates it
    empty and sizes it a moment later (a scrape then would fail), one that is removed may be
    gone; neither holds a count yet."""
    try:
        return path.stat().st_size >= _COUNTS_HEADER
    except FileNotFoundError:
        return False


class _ProcessCounts:
    """This process's own counts (no multiprocess folder): the default registry."""

    def collect(self) -> Iterator:
        yield from REGISTRY.collect()


def metrics_text(collectors: Iterable[Collector] = ()) -> bytes:
    """The exposition every web process answers /metrics with: the counts, and `collectors`
    read now (state: backlogs, queues, the chain)."""
    registry = CollectorRegistry(auto_describe=False)
    folder = multiproc_folder()
    registry.register(_HostFiles(folder.parent) if folder else _ProcessCounts())
    for collector in collectors:
        registry.register(collector)
    return generate_latest(registry)


def metrics_folder_reset() -> None:
    """Empty this service's multiprocess folder (PROMETHEUS_MULTIPROC_DIR), as its main process
    starts and before it forks the processes that count: what a previous run counted (with
    process ids that may come again) must not be added to this run's counts."""
    folder = multiproc_folder()
    if folder is None:
        return
    folder.mkdir(parents=True, exist_ok=True)
    for path in folder.glob("*.db"):
        path.unlink(missing_ok=True)
