"""What /metrics reads when scraped: state rather than events (portal/metrics.py counts those).

The chain work waiting (the anchoring backlog and its oldest record's age), the Celery queues'
depths (the lengths of their Redis lists), the chain's head and its age, the operator
account's balance and nonce, exports and alert deliveries not finished, open operator alerts,
and the free bytes of this host's disks that uploads are written to (sharing/disk.py). Cached
STATE_CACHE_SECONDS, so that several scrapers cost one round of cheap queries (counts on
indexed columns, one LLEN per queue, one JSON-RPC batch, a statvfs per folder). Each source
goes through readiness's clients (portal/health.py), with its timeouts (CHECK_TIMEOUT: a node
that does not answer costs a scrape that long, never a hang); one that fails is reported as
`authros_metrics_source_up{source} 0`, the others still are.
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
from chainworker.rpc import NodeRpc
from chainworker.selectors import operator_alerts_open_count
from chainworker.services import operator_account
from core.metrics import CachedCollector
from portal.health import chain_probe_client, redis_probe_client
from sharing.disk import portal_disks_free
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
    yield GaugeMetricFamily(
        "authros_operator_alerts_open",
        "Operator alerts open (not resolved): the admin's Operator alerts list them",
        value=operator_alerts_open_count(),
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


def _chain() -> Iterator[GaugeMetricFamily]:
    """The head and the operator's account in one JSON-RPC batch: one round trip, so a node
    that does not answer costs one CHECK_TIMEOUT."""
    address = operator_account().address
    block, balance, nonce = NodeRpc(chain_probe_client(settings.CHAIN_RPC_URL)).batch(
        [
            ("eth_getBlockByNumber", ["latest", False]),
            ("eth_getBalance", [address, "latest"]),
            ("eth_getTransactionCount", [address, "latest"]),
        ],
        label="metrics",
    )
    for answer in (block, balance, nonce):
        if isinstance(answer, Exception):
            raise answer
    yield GaugeMetricFamily(
        "authros_chain_head_block",
        "The chain's latest block number",
        value=int(block["number"], 16),
    )
    yield GaugeMetricFamily(
        "authros_chain_head_age_seconds",
        "Seconds since the chain's latest block was made",
        value=max(time.time() - int(block["timestamp"], 16), 0.0),
    )
    # Floats: a balance past 2**53 wei (0.009 ether) loses its last digits, not its meaning.
    yield GaugeMetricFamily(
        "authros_operator_balance_wei",
        "The operator account's balance on the chain, in wei (it pays for all chain work)",
        value=int(balance, 16),
    )
    yield GaugeMetricFamily(
        "authros_operator_nonce",
        "Transactions of the operator account mined (its next nonce on the chain)",
        value=int(nonce, 16),
    )


def _disks() -> Iterator[GaugeMetricFamily]:
    free = GaugeMetricFamily(
        "authros_disk_free_bytes",
        "Free bytes on this host's disks that uploads are written to, by folder: the local "
        "envelope storage's, the SQLite database's",
        labels=["folder"],
    )
    for folder, count in portal_disks_free().items():
        free.add_metric([str(folder)], count)
    yield free


SOURCES = {"database": _database, "redis": _queues, "chain": _chain, "disk": _disks}


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
