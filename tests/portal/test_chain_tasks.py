"""Chain tasks declare how they survive failures (the behaviour is tested with real workers)."""

import pytest
from celery.exceptions import SoftTimeLimitExceeded

from accounts import tasks as accounts_tasks
from chainworker.errors import ChainUnavailable, NonceError, TransactionTimeout
from chainworker.work import ChainWorkNotReady
from portal.celery import app
from sharing import tasks as sharing_tasks


@pytest.mark.parametrize(
    "task",
    [
        accounts_tasks.owner_register,
        accounts_tasks.key_rotate,
        accounts_tasks.robot_key_register,
        accounts_tasks.robot_key_revoke,
        sharing_tasks.grant_sync,
        sharing_tasks.records_anchor,
    ],
)
def test_chain_tasks_retry_transient_failures_late_acked_and_time_limited(task):
    assert set(task.autoretry_for) >= {
        ChainUnavailable,
        TransactionTimeout,
        NonceError,
        ChainWorkNotReady,
        SoftTimeLimitExceeded,
    }
    assert task.retry_backoff
    assert task.retry_jitter
    assert task.max_retries >= 10
    assert task.acks_late
    assert 0 < task.soft_time_limit < task.time_limit
    assert app.conf.worker_prefetch_multiplier == 1
