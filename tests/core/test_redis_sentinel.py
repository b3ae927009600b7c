"""The portal on Redis behind Sentinels (a master, its replica and three Sentinels: Debian's
redis-server), reached through REDIS_URL=sentinel://...?master=NAME: the caches, locks and
rate limits, and a Celery task run by a real worker process through the Sentinel broker and
result backend; then the master is killed, the Sentinels promote the replica, and the portal's
client and the same worker follow them to it."""

import os
import uuid
from collections.abc import Iterator
from datetime import timedelta

import pytest
from celery import Celery
from django.core.cache import caches
from django.utils import timezone

from accounts.decorators import page_rate_charge
from accounts.models import RobotPairing
from accounts.services.pairing import PAIRING_KEEP_EXPIRED
from chainworker.admin import celery_queue_length
from chainworker.work import ChainWorkNotReady, exclusive
from core.redis_client import get_redis
from core.redis_url import celery_redis
from sharing import cache
from stack.anvil import free_port
from stack.processes import Children, celery_worker
from tests.launchers.redis_sentinel import RedisSentinels, start_redis_sentinels
from tests.support.harness import database_url

pytestmark = pytest.mark.process

DB = 3
TASK_TIMEOUT = 120


@pytest.fixture(scope="module")
def sentinels(tmp_path_factory) -> Iterator[RedisSentinels]:
    with start_redis_sentinels(tmp_path_factory.mktemp("redis-sentinel")) as started:
        yield started


@pytest.fixture
def on_sentinels(sentinels, settings) -> str:
    """The portal's REDIS_URL names the Sentinels; get_redis() asks them for the master."""
    settings.REDIS_URL = sentinels.url(DB)
    settings.REDIS_KEY_PREFIX = f"authros-sentinel-{uuid.uuid4().hex[:8]}"
    return settings.REDIS_URL


@pytest.mark.nodb
def test_caches_locks_and_rate_limits_work_through_sentinels(on_sentinels, sentinels, settings):
    record_id = str(uuid.uuid4())
    cache.envelope_cache_put(record_id, b"envelope")
    assert cache.envelope_cache_get(record_id) == b"envelope"
    # Written on the master the Sentinels name, in the database of the URL.
    assert get_redis().connection_pool.get_master_address()[1] == sentinels.master_port()
    assert get_redis().connection_pool.connection_kwargs["db"] == DB
    with (
        exclusive("owner-9", timeout=10, wait=0),
        pytest.raises(ChainWorkNotReady),
        exclusive("owner-9", timeout=10, wait=0),
    ):
        pass
    settings.PAGE_RATE_USER = "1/hour"
    assert page_rate_charge(user_id=9) is None
    assert page_rate_charge(user_id=9) > 0
    settings.CACHES = {
        "default": {
            "BACKEND": "core.redis_client.SharedRedisCache",
            "LOCATION": on_sentinels,
            "KEY_PREFIX": settings.REDIS_KEY_PREFIX,
        }
    }
    caches["default"].set_many({"a": 1, "b": 2}, timeout=60)
    assert caches["default"].get_many(["a", "b"]) == {"a": 1, "b": 2}
    # The admin's chain status counts the Celery queue on a Sentinel broker too.
    settings.BROKER_REDIS_URL = on_sentinels
    assert celery_queue_length() == 0


@pytest.mark.worker
@pytest.mark.django_db(transaction=True)
def test_a_worker_and_the_portal_follow_a_failover(on_sentinels, sentinels, settings, tmp_path):
    queue = f"authros-sentinel-{uuid.uuid4().hex[:8]}"
    # The worker reads REDIS_URL like any portal process: its broker and results are the
    # Sentinels' master too (portal/settings.py).
    env = {
        **os.environ,
        "DJANGO_SETTINGS_MODULE": "portal.settings",
        "DATABASE_URL": database_url(),
        "REDIS_URL": on_sentinels,
        "REDIS_KEY_PREFIX": settings.REDIS_KEY_PREFIX,
        "CELERY_QUEUE": queue,
        "CHAIN_RPC_URL": f"http://127.0.0.1:{free_port()}",  # no chain: not needed here
        "AUTHROS_VAR_DIR": str(tmp_path / "var"),
        "AUTHROS_SECRETS_DIR": str(settings.SECRETS_DIR),
        "AUTHROS_MEDIA_ROOT": str(settings.MEDIA_ROOT),
        "PYTHONUNBUFFERED": "1",
    }
    children = Children(tmp_path / "logs")
    children.spawn("worker", celery_worker("sentinel", queues=[queue]), env=env)
    # The test sends as a web process would, to the broker given in the same URL.
    broker = celery_redis(on_sentinels, setting="CELERY_BROKER_URL")
    # Not the current app: the portal's shared tasks must keep sending to the portal's broker
    # in the tests that follow, not to these Sentinels once they are stopped.
    sender = Celery("sentinel-test", broker=broker.url, backend=broker.url, set_as_current=False)
    sender.conf.broker_transport_options = broker.transport_options
    sender.conf.result_backend_transport_options = broker.transport_options
    try:
        assert _purged_by_worker(sender, queue, children) == 1

        record_id = str(uuid.uuid4())
        cache.envelope_cache_put(record_id, b"kept")
        assert get_redis().wait(1, 5000) == 1  # on the replica too before the master goes
        old = sentinels.kill_master()
        new = sentinels.await_failover(old)

        # The same client (and connection pool) of the portal finds the new master.
        assert cache.envelope_cache_get(record_id) == b"kept"
        assert get_redis().connection_pool.get_master_address()[1] == new
        with exclusive("after-failover", timeout=10, wait=0):
            pass
        # The same worker reconnects to the new master and answers through it.
        assert _purged_by_worker(sender, queue, children) == 1
    finally:
        sender.close()
        children.stop_all()


def _purged_by_worker(sender: Celery, queue: str, children: Children) -> int:
    """One stale pairing request, purged by the worker's task: what its result says."""
    long_ago = timezone.now() - PAIRING_KEEP_EXPIRED - timedelta(minutes=1)
    RobotPairing.objects.create(
        code=uuid.uuid4().hex[:16],
        secret_hash="0" * 64,
        name="stale",
        public_key="04" + "1" * 128,
        expires_at=long_ago,
    )
    result = sender.send_task("accounts.tasks.robot_pairings_purge", queue=queue)
    try:
        return result.get(timeout=TASK_TIMEOUT)
    except Exception:
        children.check_alive()
        raise
