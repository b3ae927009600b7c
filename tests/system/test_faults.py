"""Fault tests with real processes: anvil, Celery workers and beat, Redis.

Each breaks the chain or the queue under the portal (a node killed and restarted empty,
blocks reverted, a worker killed while it reconciles, Redis flushed during a resync, an
owner's account emptied on a chain with gas prices) and ends the same way: every record
anchored exactly once on the chain that is live at the end, every grant as its owner set it,
nothing lost and nothing failed. Reconciliation runs every 3 s here (RECONCILE_INTERVAL).
"""

import base64
import time

import pytest
import requests

from accounts.models import ChainState, EoaFunding, Owner
from accounts.services.funding import TOPUP_REASON
from accounts.services.keys import key_rotate
from chainworker import services as chain_services
from chainworker.errors import ChainError
from core.redis_client import get_redis, redis_key
from sharing.models import Grant, Record
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.reconcile import RECONCILE_LOCK, chain_resync
from sharing.services.uploads import record_create, record_create_batch
from smcrypto import sm4
from tests.support.anchoring_checks import assert_anchored_exactly_once, records_on_chain
from tests.support.harness import WorkerStack, wait_for
from tests.support.robot_setup import RobotSetup
from tests.support.worker_robots import registered_robots, uploading

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]

# Reconciliation every 3 s, the "same chain?" verdict kept 1 s: a fault is seen in seconds.
FAST_RECONCILE = {"RECONCILE_INTERVAL": "3", "CHAIN_IDENTITY_CACHE_SECONDS": "1"}
SETTLE_TIMEOUT = 300


@pytest.fixture
def fault_stack(worker_stack, settings):
    """A worker_stack with fast reconciliation, in the test process too."""

    def make(*, workers: int, env_overrides: dict[str, str] | None = None) -> WorkerStack:
        settings.CHAIN_IDENTITY_CACHE_SECONDS = 1
        return worker_stack(
            workers=workers, env_overrides={**FAST_RECONCILE, **(env_overrides or {})}
        )

    return make


def _upload(setups: list[RobotSetup], *, rounds: range, per_batch: int) -> None:
    """`per_batch` envelopes per owner per round, through the upload service (as the API)."""
    for round_number in rounds:
        for setup in setups:
            first = round_number * per_batch + 1
            record_create_batch(
                robot=setup.robot,
                envelopes=[setup.seal(seq) for seq in range(first, first + per_batch)],
            )


def _upload_http(
    stack: WorkerStack, setups: list[RobotSetup], *, rounds: range, per_batch: int
) -> None:
    """As `_upload`, but as the robots' agents do it: batch POSTs to the portal (gunicorn)."""
    for round_number in rounds:
        for setup in setups:
            first = round_number * per_batch + 1
            envelopes = [setup.seal(seq) for seq in range(first, first + per_batch)]
            answer = requests.post(
                f"{stack.web_url}/api/v1/records/",
                json={"envelopes": [base64.b64encode(e).decode() for e in envelopes]},
                headers={"Authorization": f"Token {setup.token}"},
                timeout=60,
            )
            assert answer.status_code == 201, answer.text
            assert len(answer.json()) == per_batch


def _grants_set(alice: RobotSetup, bob: RobotSetup, carol: RobotSetup, dave: RobotSetup) -> dict:
    """alice grants bob; carol grants dave and revokes it: both settled on chain."""
    grant_create(owner=alice.owner, grantee=bob.owner)
    grant_create(owner=carol.owner, grantee=dave.owner)
    wait_for(
        lambda: Grant.objects.filter(status=Grant.Status.ACTIVE).count() == 2,
        timeout=120,
        what="two grants on chain",
    )
    grant_revoke(owner=carol.owner, grantee=dave.owner)
    wait_for(
        lambda: Grant.objects.filter(status=Grant.Status.REVOKED).count() == 1,
        timeout=120,
        what="the revocation on chain",
    )
    return {(alice.owner, bob.owner): True, (carol.owner, dave.owner): False}


def _settled(records: int) -> bool:
    """The database says all is done and the live chain holds as many records."""
    if Record.objects.exclude(status=Record.Status.ANCHORED).exists():
        return False
    if Owner.objects.exclude(chain_state=ChainState.CONFIRMED).exists():
        return False
    if Grant.objects.exclude(status__in=[Grant.Status.ACTIVE, Grant.Status.REVOKED]).exists():
        return False
    try:
        if chain_services.chain_identity().state != chain_services.IDENTITY_SAME:
            return False
        return records_on_chain(chain_services.chain_client()) == records
    except ChainError:
        return False


def _wait_settled(stack: WorkerStack, records: int) -> None:
    try:
        wait_for(
            lambda: _settled(records),
            timeout=SETTLE_TIMEOUT,
            what=f"{records} records anchored on the live chain",
            interval=1,
        )
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{stack.worker_logs()[-4000:]}") from None


def _assert_end_state(records: int, grants: dict[tuple[Owner, Owner], bool]) -> None:
    """Every record anchored exactly once on the live chain with its digest and owner, every
    grant as its owner set it, every owner registered with its newest key; none failed."""
    assert chain_services.chain_identity().state == chain_services.IDENTITY_SAME
    client = chain_services.chain_client()
    assert Record.objects.count() == records
    assert not Record.objects.exclude(status=Record.Status.ANCHORED).exists()
    assert not Record.objects.exclude(failure_reason="").exists()
    assert_anchored_exactly_once(client)
    assert records_on_chain(client) == records
    for (owner, grantee), access in grants.items():
        assert client.has_access(owner.eoa_address, grantee.eoa_address) is access
    for owner in Owner.objects.all():
        assert client.is_registered(owner.eoa_address)
        newest = owner.keys.order_by("-created_at").first()
        assert "0x" + client.commitment_of(owner.eoa_address).hex() == newest.commitment.lower()


def test_anvil_killed_and_restarted_empty_during_a_thousand_uploads(fault_stack):
    """A development chain lost everything mid-run: the portal sees the reset, deploys again
    and re-creates owners, grants and records from the database, while the robots' uploads
    go on through the portal (gunicorn)."""
    stack = fault_stack(workers=2)
    stack.start_web()
    setups = registered_robots(4)
    grants = _grants_set(*setups)
    _upload_http(stack, setups, rounds=range(5), per_batch=25)  # 500 records
    stack.reset_anvil()
    _upload_http(stack, setups, rounds=range(5, 10), per_batch=25)  # 500 more, while it recovers
    assert Record.objects.count() == 1000
    _wait_settled(stack, 1000)
    _assert_end_state(1000, grants)
    assert "chain reset detected on a development chain" in stack.worker_logs()


def test_anvil_reverted_ten_blocks(fault_stack):
    """The node lost its last 10 blocks (anvil_rollback): the records and the grant the
    database says are on chain in them are sent again by the reconciliation."""
    stack = fault_stack(workers=1)
    alice, bob = registered_robots(2)
    for seq in range(1, 21):
        record = record_create(robot=alice.robot, data=alice.seal(seq))
        wait_for(
            lambda r=record: Record.objects.get(pk=r.pk).status == Record.Status.ANCHORED,
            timeout=60,
            what=f"record {seq} anchored",
        )
        if seq == 15:
            grant = grant_create(owner=alice.owner, grantee=bob.owner)
            wait_for(
                lambda g=grant: Grant.objects.get(pk=g.pk).status == Grant.Status.ACTIVE,
                timeout=60,
                what="the grant on chain",
            )
    client = chain_services.chain_client()
    head = client.latest_block()
    lost = set(Record.objects.filter(block_number__gt=head - 10).values_list("pk", flat=True))
    stack.anvil_rpc("anvil_rollback", 10)
    assert lost
    assert all(client.data_query(pk, owner=alice.owner.eoa_address) is None for pk in lost)
    assert not client.has_access(alice.owner.eoa_address, bob.owner.eoa_address)
    _wait_settled(stack, 20)
    _assert_end_state(20, {(alice.owner, bob.owner): True})
    assert "the chain lost" in stack.worker_logs()


def test_anvil_killed_after_blocks_it_never_wrote_while_a_robot_uploads(fault_stack):
    """kill -9 of the node: the blocks it mined since its last state write are gone with the
    roots in them, and the owner's nonce counter is ahead of what the restarted node knows. The
    root sent next waits behind the nonce gap for ever (the receipt timeout here is an hour):
    it is seen as never to be mined and sent again from the node's count; the lost roots are
    sent again by the reconciliation. That runs every 30 s here, so the anchoring after the
    restart meets the gap first (a reconciliation resyncs the counter, which would hide it)."""
    stack = fault_stack(
        workers=1, env_overrides={"CHAIN_RECEIPT_TIMEOUT": "3600", "RECONCILE_INTERVAL": "30"}
    )
    (setup,) = registered_robots(1)
    with uploading(setup) as uploaded:
        time.sleep(2)
        assert stack.anvil.keeper is not None
        stack.anvil.keeper.write()
        written = Record.objects.filter(status=Record.Status.ANCHORED).count()
        # Several roots' worth (one every 0.5 s or so): some are surely in blocks mined after
        # the write.
        wait_for(
            lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() > written + 10,
            timeout=60,
            what="records anchored in blocks the state file lacks",
        )
        stack.kill_anvil()
        stack.restart_anvil()
        time.sleep(3)
    _wait_settled(stack, len(uploaded))
    _assert_end_state(len(uploaded), {})
    logs = stack.worker_logs()
    assert "the chain lost" in logs  # the kill did lose anchored roots
    assert "will never be mined" in logs


def test_a_full_chain_reset_with_grants_and_a_rotated_key(fault_stack):
    """A new empty anvil where the old one was, once everything had settled: active and
    revoked grants, a rotated key and the records are all as before on the new chain."""
    stack = fault_stack(workers=1)
    setups = registered_robots(4)
    grants = _grants_set(*setups)
    new_key = key_rotate(owner=setups[1].owner, sm4_key=sm4.generate_key())
    _upload(setups, rounds=range(2), per_batch=10)
    wait_for(
        lambda: type(new_key).objects.get(pk=new_key.pk).chain_state == ChainState.CONFIRMED,
        timeout=60,
        what="the rotated key on chain",
    )
    _wait_settled(stack, 80)
    stack.reset_anvil()
    _wait_settled(stack, 80)
    _assert_end_state(80, grants)


def test_worker_killed_during_reconciliation(fault_stack, settings):
    """The chain lost 600 records (reverted to a snapshot taken before them); the only worker
    is killed while it reconciles; a new worker finishes the repair, nothing anchored twice."""
    stack = fault_stack(workers=1, env_overrides={"RECONCILE_CHUNK": "2000"})
    alice, bob = registered_robots(2)
    snapshot = stack.anvil_rpc("evm_snapshot")
    _upload([alice, bob], rounds=range(3), per_batch=100)
    _wait_settled(stack, 600)
    stack.anvil_rpc("evm_revert", snapshot)
    assert chain_services.chain_client().record_count() == 0
    lock = get_redis().lock(redis_key("work", RECONCILE_LOCK))
    wait_for(lock.locked, timeout=60, what="a reconciliation under way", interval=0.02)
    stack.kill_worker("w0")
    stack.start_worker("w1")
    _wait_settled(stack, 600)
    _assert_end_state(600, {})


def test_redis_flushed_during_a_resync(fault_stack):
    """`manage.py chain_resync` queues everything again; Redis then loses the queue, the locks,
    the nonce counters: the sweeps queue the work again and it all ends on chain once."""
    stack = fault_stack(workers=2)
    setups = registered_robots(4)
    grants = _grants_set(*setups)
    _upload(setups, rounds=range(3), per_batch=20)
    _wait_settled(stack, 240)
    chain_resync()
    assert stack.redis_flush_own() > 0
    wait_for(
        lambda: (
            Record.objects.filter(status=Record.Status.ANCHORED).exists()
            or Owner.objects.filter(chain_state=ChainState.CONFIRMED).exists()
        ),
        timeout=60,
        what="the workers to take up the resync",
    )
    stack.redis_flush_own()  # again, with the workers in the middle of it
    _upload(setups, rounds=range(3, 4), per_batch=20)
    _wait_settled(stack, 320)
    _assert_end_state(320, grants)


def test_an_owner_account_emptied_mid_run_on_a_chain_with_gas_prices(fault_stack):
    """anvil's own fees (1 gwei base fee): alice's account is emptied mid-run; the operator
    tops it up, and every record is anchored, none failed, none left waiting for gas."""
    stack = fault_stack(workers=1)
    alice, bob = registered_robots(2)
    client = chain_services.chain_client()
    assert client.fee_per_gas() > 0
    _upload([alice, bob], rounds=range(5), per_batch=20)
    stack.anvil_rpc("anvil_setBalance", alice.owner.eoa_address, "0x0")
    _upload([alice, bob], rounds=range(5, 10), per_batch=20)
    _wait_settled(stack, 400)
    _assert_end_state(400, {})
    assert EoaFunding.objects.filter(owner=alice.owner, reason=TOPUP_REASON).exists()
