"""The portal on a real Redis Cluster (three masters, redis-server from Debian), reached through
REDIS_URL=redis+cluster://...: every script names the keys it touches and the keys of one
script share a slot (hash tags), which a cluster requires and redis-py's cluster client checks;
the locks, nonces, rate limits, the budget of checks and Django's cache work on it; Celery's
broker cannot be one."""

import os
import subprocess
import time
import uuid
from collections.abc import Iterator

import pytest
import redis
from django.core.cache import caches
from rest_framework.request import Request

from accounts import signup_limits
from accounts.authentication import AnonRateThrottle
from accounts.decorators import page_rate_charge
from chainworker.nonces import RedisNonceManager
from chainworker.work import ChainWorkNotReady, exclusive
from core.redis_client import get_redis
from core.redis_url import RedisUrlError, celery_redis
from sharing import cache
from sharing.errors import CheckBudgetExceeded
from sharing.verification.budget import checks_charge, checks_refund
from stack.anvil import free_port
from stack.processes import PYTHON, REPO_ROOT
from tests.launchers.redis_cluster import RedisCluster, start_redis_cluster

pytestmark = [pytest.mark.process, pytest.mark.nodb]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory) -> Iterator[RedisCluster]:
    with start_redis_cluster(tmp_path_factory.mktemp("redis-cluster")) as started:
        yield started


@pytest.fixture
def on_cluster(cluster, settings) -> redis.RedisCluster:
    """The portal's REDIS_URL is the cluster: get_redis() is redis-py's cluster client."""
    settings.REDIS_URL = cluster.url()
    settings.REDIS_KEY_PREFIX = f"authros-cluster-{uuid.uuid4().hex[:8]}"
    client = get_redis()
    assert isinstance(client, redis.RedisCluster)
    return client


def test_the_envelope_cache_keeps_its_bounds_on_a_cluster(on_cluster, settings):
    settings.ENVELOPE_CACHE_MAX_BYTES = 3000
    settings.ENVELOPE_CACHE_TTL = 60
    ids = [str(uuid.uuid4()) for _ in range(5)]
    now = int(time.time() * 1000)  # each entry a millisecond later: "oldest" is well defined
    for offset, record_id in enumerate(ids):
        cache.envelope_cache_put(record_id, bytes([offset]) * 1000, now_ms=now + offset)
    assert [cache.envelope_cache_get(record_id) for record_id in ids] == [
        None,
        None,
        b"\x02" * 1000,
        b"\x03" * 1000,
        b"\x04" * 1000,
    ]
    assert cache.envelope_cache_bytes() == 3000
    cache.envelope_cache_evict(ids[4])
    assert cache.envelope_cache_get(ids[4]) is None
    assert cache.envelope_cache_bytes() == 2000
    # The entries are spread over the cluster's nodes no more than the bookkeeping: one slot.
    slots = {on_cluster.keyslot(key) for key in cache._keys(ids[2])}
    assert len(slots) == 1


def test_a_batch_is_cached_in_one_pipeline_on_a_cluster(on_cluster, settings):
    settings.ENVELOPE_CACHE_MAX_BYTES = 10_000
    items = [(str(uuid.uuid4()), b"e" * 100) for _ in range(20)]
    cache.envelope_cache_put_many(items)
    assert all(cache.envelope_cache_get(record_id) == data for record_id, data in items)
    assert cache.envelope_cache_bytes() == 2000


def test_the_signup_limits_hold_on_a_cluster(on_cluster, settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "2/hour"
    settings.SIGNUP_RATE_TOTAL = "100/hour"
    taken = [signup_limits.signup_slot_take(address="10.0.0.7") for _ in range(3)]
    assert [slot.allowed for slot in taken] == [True, True, False]
    assert taken[2].retry_after > 0
    signup_limits.signup_slot_give_back(taken[1])
    assert signup_limits.signup_slot_take(address="10.0.0.7").allowed


def test_locks_and_nonces_hold_on_a_cluster(on_cluster):
    # Held, the lock is refused to a second taker.
    with (
        exclusive("owner-7", timeout=10, wait=0),
        pytest.raises(ChainWorkNotReady),
        exclusive("owner-7", timeout=10, wait=0),
    ):
        pass
    with exclusive("owner-7", timeout=10, wait=0):
        pass  # released: taken again
    nonces = RedisNonceManager(on_cluster, namespace="cluster-test", prefix="authros-cluster")
    with nonces.reserve("0xAbC", lambda address: 5) as reservation:
        assert reservation.nonce == 5
        reservation.commit()
    with nonces.reserve("0xabc", lambda address: 5) as reservation:
        assert reservation.nonce == 6
    nonces.forget("0xabc")


def test_rate_limits_count_on_a_cluster(on_cluster, settings, rf):
    settings.PAGE_RATE_USER = "2/hour"
    charged = [page_rate_charge(user_id=7) for _ in range(3)]
    assert charged[:2] == [None, None]
    assert charged[2] > 0  # over the limit: the seconds until the window ends
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "anon": "2/minute",
        },
    }

    def allowed() -> bool:
        request = Request(rf.get("/api/v1/sm2-public-key/", REMOTE_ADDR="203.0.113.77"))
        return AnonRateThrottle().allow_request(request, view=None)

    assert [allowed() for _ in range(3)] == [True, True, False]


def test_the_budget_of_checks_counts_on_a_cluster(on_cluster, settings):
    settings.CHECK_BUDGET = "5/day"
    checks_charge(caller_id=7, records=3)
    with pytest.raises(CheckBudgetExceeded):
        checks_charge(caller_id=7, records=3)  # 2 left: refused, nothing taken
    checks_charge(caller_id=7, records=2)
    checks_refund(caller_id=7, records=1)
    checks_charge(caller_id=7, records=1)
    with pytest.raises(CheckBudgetExceeded):
        checks_charge(caller_id=7, records=1)
    checks_charge(caller_id=8, records=5)  # another caller's budget


def test_djangos_cache_works_on_a_cluster(cluster, settings):
    settings.CACHES = {
        "default": {
            "BACKEND": "core.redis_client.SharedRedisCache",
            "LOCATION": cluster.url(),
            "KEY_PREFIX": f"authros-cluster-{uuid.uuid4().hex[:8]}",
        }
    }
    django_cache = caches["default"]
    django_cache.set_many({f"k{n}": n for n in range(10)}, timeout=60)
    # Ten keys in several slots: read slot by slot, where one MGET would be refused.
    assert django_cache.get_many([f"k{n}" for n in range(10)]) == {f"k{n}": n for n in range(10)}
    django_cache.delete_many([f"k{n}" for n in range(10)])
    assert django_cache.get("k3") is None


def test_a_cluster_cannot_be_the_celery_broker(cluster):
    """A worker pointed at a cluster (REDIS_URL, and CELERY_BROKER_URL not set apart) refuses
    to start, and says what to do."""
    env = {**os.environ, "DJANGO_SETTINGS_MODULE": "portal.settings", "REDIS_URL": cluster.url()}
    started = subprocess.run(
        [PYTHON, "-m", "celery", "-A", "portal", "worker", "--pool", "solo"],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert started.returncode != 0
    assert "REDIS_URL is a Redis Cluster, which cannot be Celery's broker" in started.stderr
    assert "set CELERY_BROKER_URL to a plain redis:// or a sentinel:// Redis" in started.stderr
    # Named as the broker itself, it is refused too (the settings read it with celery_redis).
    with pytest.raises(RedisUrlError, match="CELERY_BROKER_URL is a Redis Cluster"):
        celery_redis(cluster.url(), setting="CELERY_BROKER_URL")


def test_a_cluster_that_does_not_answer_is_redis_unavailable(settings, tmp_path):
    """redis-py says so with its RedisClusterException, no RedisError; the portal's client
    makes it a ConnectionError, so what works without Redis goes on working (no 500)."""
    settings.PAGE_RATE_USER = "1/hour"
    settings.REDIS_URL = f"redis+cluster://127.0.0.1:{free_port()}"  # nobody there
    assert page_rate_charge(user_id=3) is None  # served uncounted
    assert cache.envelope_cache_get(str(uuid.uuid4())) is None  # a miss
    with start_redis_cluster(tmp_path / "cluster") as gone:
        settings.REDIS_URL = gone.url()
        assert page_rate_charge(user_id=3) is None
        assert page_rate_charge(user_id=3) > 0
    # Stopped under a client that knew it.
    assert page_rate_charge(user_id=3) is None
    with pytest.raises(redis.ConnectionError):
        get_redis().get("anything")
