"""Real Celery workers, Redis and anvil: everything is anchored exactly once, whatever fails.

These tests start worker and beat processes (tests/support/harness.py) that share the test database,
a Redis database of their own and an anvil node, then break things: kill -9 a worker in the
middle of a batch, stop the chain for 20 s, flush Redis, change stored ciphertext.
"""

import re
import time

import pytest
import redis

from accounts.models import ChainState
from accounts.services import keys as account_keys
from chainworker import services as chain_services
from sharing.cache import _key as cache_key
from sharing.models import Grant, Record
from sharing.services import anchoring as sharing_anchoring
from sharing.services import grants as sharing_grants
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create, record_create_batch
from sharing.storage import envelope_storage
from sharing.tasks import records_verify
from smcrypto import sm4
from tests.support.anchoring_checks import assert_anchored_exactly_once, records_on_chain
from tests.support.harness import WorkerStack, wait_for
from tests.support.worker_robots import registered_robots, uploading

_ANCHOR_RUN_DONE = r"Task sharing\.tasks\.records_anchor\[[^\]]+\] succeeded"

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]


def _all_anchored(count: int, *, timeout: float) -> None:
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == count,
        timeout=timeout,
        what=f"{count} records anchored",
        interval=0.5,
    )


def _assert_each_anchored_exactly_once(stack: WorkerStack) -> None:
    client = chain_services.chain_client()
    assert not Record.objects.exclude(status=Record.Status.ANCHORED).exists()
    assert_anchored_exactly_once(client)
    assert records_on_chain(client) == Record.objects.count()
    logs = stack.worker_logs()
    assert "NonceError" not in logs
    assert "nonce" not in logs.lower() or "refused for" not in logs


def test_thousand_uploads_from_ten_owners_with_two_workers(worker_stack):
    stack = worker_stack(workers=2)
    setups = registered_robots(10)
    next_seq = dict.fromkeys(range(10), 1)
    for round_number in range(10):
        for index, setup in enumerate(setups):
            seq = next_seq[index]
            if round_number % 2:
                record_create_batch(
                    robot=setup.robot, envelopes=[setup.seal(s) for s in range(seq, seq + 10)]
                )
            else:
                for s in range(seq, seq + 10):
                    record_create(robot=setup.robot, data=setup.seal(s))
            next_seq[index] = seq + 10
    assert Record.objects.count() == 1000
    _all_anchored(1000, timeout=300)
    _assert_each_anchored_exactly_once(stack)
    # Records of one owner share transactions: far fewer transactions than records.
    transactions = Record.objects.values("tx_hash").distinct().count()
    assert transactions < 500


def test_worker_killed_in_the_middle_of_a_batch(worker_stack):
    stack = worker_stack(workers=1, block_time=2)
    (setup,) = registered_robots(1)
    record_create_batch(robot=setup.robot, envelopes=[setup.seal(s) for s in range(1, 51)])
    # The batch is sent and the worker waits for its block: kill it there.
    wait_for(
        lambda: Record.objects.filter(anchor_attempts__gte=1).exists(),
        timeout=60,
        what="the worker to send the batch",
        interval=0.05,
    )
    stack.kill_worker("w0")
    assert Record.objects.filter(status=Record.Status.PENDING).exists()
    record_create_batch(robot=setup.robot, envelopes=[setup.seal(s) for s in range(51, 61)])
    stack.start_worker("w0-restarted")
    _all_anchored(60, timeout=180)
    _assert_each_anchored_exactly_once(stack)


def test_chain_down_for_twenty_seconds(worker_stack):
    stack = worker_stack(workers=1)
    (setup,) = registered_robots(1)
    with uploading(setup) as uploaded:
        time.sleep(3)
        stack.stop_anvil()
        time.sleep(20)
        assert Record.objects.filter(status=Record.Status.PENDING).exists()
        stack.restart_anvil()
        time.sleep(3)
    _all_anchored(len(uploaded), timeout=180)
    _assert_each_anchored_exactly_once(stack)
    # About a hundred uploads met the outage: they waited for the one run retrying, rather than
    # each queueing a run that retried on its own (95 runs retried 438 times, before).
    retried = set(re.findall(r"records_anchor\[([^\]]+)\] retry:", stack.worker_logs()))
    assert 0 < len(retried) < 10


def test_redis_flushed_during_uploads(worker_stack):
    stack = worker_stack(workers=2)
    setups = registered_robots(2)
    for seq in range(1, 101):
        for setup in setups:
            record_create(robot=setup.robot, data=setup.seal(seq))
        if seq == 50:
            stack.redis_flush_own()
    _all_anchored(200, timeout=180)
    _assert_each_anchored_exactly_once(stack)


def test_tampered_cache_and_durable_copy_are_refused(worker_stack):
    stack = worker_stack(workers=1)
    (setup,) = registered_robots(1)
    first = record_create(robot=setup.robot, data=setup.seal(1))
    second = record_create(robot=setup.robot, data=setup.seal(2))
    _all_anchored(2, timeout=60)

    def verdict(record: Record) -> str:
        return records_verify.delay([str(record.pk)], setup.owner.pk).get(timeout=60)[0]["outcome"]

    assert verdict(first) == "verified"
    cache = redis.Redis.from_url(stack.redis_url)
    changed = bytearray(cache.get(cache_key(first.pk)))
    changed[-1] ^= 0x01
    cache.set(cache_key(first.pk), bytes(changed))
    assert verdict(first) == "tampered"

    cache.delete(cache_key(second.pk))
    path = envelope_storage().path(second.storage_name)
    with open(path, "r+b") as handle:
        data = bytearray(handle.read())
        data[30] ^= 0x01
        handle.seek(0)
        handle.write(bytes(data))
    assert verdict(second) == "tampered"
    assert verdict(second) == "tampered"


def test_views_are_checked_on_their_own_queue_with_no_chain_worker_left(worker_stack):
    """A worker on the verify queue alone answers views; chain work never reaches it."""
    stack = worker_stack(workers=1)
    stack.start_worker("verifier", queues=[f"{stack.queue}-verify"])
    (setup,) = registered_robots(1)
    record = record_create(robot=setup.robot, data=setup.seal(1))
    _all_anchored(1, timeout=60)
    stack.kill_worker("w0")  # the only worker for chain work

    later = record_create(robot=setup.robot, data=setup.seal(2))
    view = records_verify.delay([str(record.pk)], setup.owner.pk).get(timeout=60)[0]

    assert view["outcome"] == "verified"
    verifier_log = (stack.logs / "verifier.log").read_text()
    assert "Task sharing.tasks.records_verify[" in verifier_log
    assert "Task sharing.tasks.records_anchor[" not in verifier_log
    assert "Task accounts.tasks.owner_register[" not in verifier_log
    assert Record.objects.get(pk=later.pk).status == Record.Status.PENDING


def test_revoked_viewer_is_refused_at_the_next_view(worker_stack):
    worker_stack(workers=1)
    alice, bob = registered_robots(2)
    record = record_create(robot=alice.robot, data=alice.seal(1))
    _all_anchored(1, timeout=60)
    grant = grant_create(owner=alice.owner, grantee=bob.owner)
    wait_for(
        lambda: Grant.objects.get(pk=grant.pk).status == Grant.Status.ACTIVE,
        timeout=60,
        what="the grant on chain",
    )
    view = records_verify.delay([str(record.pk)], bob.owner.pk).get(timeout=60)[0]
    assert view["outcome"] == "verified"
    grant_revoke(owner=alice.owner, grantee=bob.owner)
    view = records_verify.delay([str(record.pk)], bob.owner.pk).get(timeout=60)[0]
    assert view["outcome"] == "no_access"
    wait_for(
        lambda: Grant.objects.get(pk=grant.pk).status == Grant.Status.REVOKED,
        timeout=60,
        what="the revocation on chain",
    )
    client = chain_services.chain_client()
    assert not client.has_access(alice.owner.eoa_address, bob.owner.eoa_address)


def test_owners_take_turns_and_transactions_share_blocks(worker_stack):
    """A long backlog of one owner does not hold up another, and one owner has several
    batch transactions in flight at once (so they share blocks)."""
    worker_stack(
        workers=1,
        block_time=1,
        env_overrides={"ANCHOR_BATCH_MAX": "5", "ANCHOR_ROOT_MAX": "5", "ANCHOR_INFLIGHT": "4"},
    )
    busy, quiet = registered_robots(2)
    record_create_batch(robot=busy.robot, envelopes=[busy.seal(s) for s in range(1, 101)])
    late = record_create(robot=quiet.robot, data=quiet.seal(1))
    _all_anchored(101, timeout=180)
    late.refresh_from_db()
    last_of_busy = Record.objects.filter(owner=busy.owner).order_by("-anchored_at").first()
    assert late.anchored_at < last_of_busy.anchored_at
    busy_blocks = set(
        Record.objects.filter(owner=busy.owner).values_list("block_number", flat=True)
    )
    busy_transactions = set(
        Record.objects.filter(owner=busy.owner).values_list("tx_hash", flat=True)
    )
    assert len(busy_transactions) == 20
    assert len(busy_blocks) < len(busy_transactions)


def test_work_whose_messages_the_broker_lost_is_queued_again_by_the_beat_sweep(
    worker_stack, monkeypatch
):
    stack = worker_stack(workers=1)
    alice, bob = registered_robots(2)
    # A registration ends by queueing an anchoring run for its owner; let those runs finish,
    # or one still running would itself queue the anchoring the broker is about to "lose".
    wait_for(
        lambda: len(re.findall(_ANCHOR_RUN_DONE, stack.worker_logs())) >= 2,
        timeout=60,
        what="the anchoring runs queued by the registrations",
    )
    lost: list[str] = []

    def broker_lost(task_name, *args, countdown=None):
        lost.append(task_name.rpartition(".")[2])
        return False

    for module in (sharing_grants, sharing_anchoring, account_keys):
        monkeypatch.setattr(module, "enqueue", broker_lost)
    for seq in range(1, 6):
        record_create(robot=alice.robot, data=alice.seal(seq))
    grant = grant_create(owner=alice.owner, grantee=bob.owner)
    new_key = account_keys.key_rotate(owner=bob.owner, sm4_key=sm4.generate_key())
    assert set(lost) == {"records_anchor", "grant_sync", "key_rotate"}

    # Only the beat's sweep (every 2 s, for work pending over 5 s) can queue them now.
    _all_anchored(5, timeout=90)
    wait_for(
        lambda: Grant.objects.get(pk=grant.pk).status == Grant.Status.ACTIVE,
        timeout=60,
        what="the grant on chain",
    )
    wait_for(
        lambda: type(new_key).objects.get(pk=new_key.pk).chain_state == ChainState.CONFIRMED,
        timeout=60,
        what="the rotated key on chain",
    )
    assert "sharing.tasks.chain_work_sweep" in (stack.logs / "beat.log").read_text()
    _assert_each_anchored_exactly_once(stack)
