"""What /metrics reads when scraped: state rather than events (portal/metrics.py counts those).

The chain work waiting (the anchoring backlog and its oldest record's age), the Celery queues'
depths (the lengths of their Redis lists), the chain's head and its age, exports and alert
deliveries not finished. Cached STATE_CACHE_SECONDS, so that several scrapers cost one round of
cheap queries (counts on indexed columns, one LLEN per queue, one block). Each source goes
through readiness's clients (portal/health.py), with its timeouts; one that fails is reported
as `authros_metrics_source_up{source} 0`, the others still are.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator

from celery import current_app
from django.conf import settings
from django.utils import timezone
from prometheus_client.core import GaugeMetricFamily

from alerts.selectors import alert_deliveries_pending_count
from chainworker.backlog import backlog_counts
from core.metrics import CachedCollector
from portal.health import chain_probe_client, redis_probe_client
from sharing.selectors.activity import record_oldest_pending_since
from sharing.selectors.exports import export_counts_unfinished

logger = logging.getLogger(__name__)

STATE_CACHE_SECONDS = 5.0
# kombu's Redis transport keeps a queue's messages of priority p > 0 in "<queue>\x06\x16<p>".
_PRIORITY_SUFFIXES = ("", "\x06\x163", "\x06\x166", "\x06\x169")


def _database() -> Iterator[GaugeMetricFamily]:
    backlog = GaugeMetricFamily(
        "authros_chain_backlog", "Chain work waiting in the database, by kind", labels=["kind"]
    )
    for kind, count in sorted(backlog_counts().items()):
        backlog.add_metric([kind], count)
    yield backlog
    oldest = record_oldest_pending_since()
    age = (timezone.now() - oldest).total_seconds() if oldest is not None else 0.0
    yield GaugeMetricFamily(
        "authros_anchoring_oldest_pending_seconds",
        "Age of the oldest record waiting for anchoring (0: none waits)",
        value=max(age, 0.0),
    )
    exports = GaugeMetricFamily(
        "authros_exports_unfinished", "Exports queued or running, by status", labels=["status"]
    )
    for status, count in export_counts_unfinished().items():
        exports.add_metric([status], count)
    yield exports
    yield GaugeMetricFamily(
        "authros_alert_deliveries_pending",
        "Alert deliveries not sent yet and not given up",
        value=alert_deliveries_pending_count(),
    )


def _queues() -> Iterator[GaugeMetricFamily]:
    conf = current_app.conf  # the queue names as the running app has them (tests change them)
    names = [conf.task_default_queue, conf.task_default_queue + conf.verify_queue_suffix]
    client = redis_probe_client(settings.BROKER_REDIS_URL)
    pipe = client.pipeline(transaction=False)
    for name in names:
        for suffix in _PRIORITY_SUFFIXES:
            pipe.llen(name + suffix)
    lengths = pipe.execute()
    depths = GaugeMetricFamily(
        "authros_celery_queue_length", "Messages waiting in each Celery queue", labels=["queue"]
    )
    step = len(_PRIORITY_SUFFIXES)
    for index, name in enumerate(names):
        depths.add_metric([name], sum(lengths[index * step : (index + 1) * step]))
    yield depths


def _chain_head() -> Iterator[GaugeMetricFamily]:
    block = chain_probe_client(settings.CHAIN_RPC_URL).eth.get_block("latest")
    yield GaugeMetricFamily(
        "authros_chain_head_block", "The chain's latest block number", value=int(block["number"])
    )
    yield GaugeMetricFamily(
        "authros_chain_head_age_seconds",
        "Seconds since the chain's latest block was made",
        value=max(time.time() - int(block["timestamp"]), 0.0),
    )


SOURCES = {"database": _database, "redis": _queues, "chain": _chain_head}


def _state() -> Iterator[GaugeMetricFamily]:
    up = GaugeMetricFamily(
        "authros_metrics_source_up",
        "Whether a source of the scrape-time metrics answered (1) or not (0)",
        labels=["source"],
    )
    for source, read in SOURCES.items():
        try:
            families = list(read())
        except Exception as exc:  # one source down must not hide the others
            logger.warning("metrics: %s did not answer: %s", source, exc.__class__.__name__)
            up.add_metric([source], 0)
            continue
        up.add_metric([source], 1)
        yield from families
    yield up


state_collector = CachedCollector(_state, seconds=STATE_CACHE_SECONDS)
