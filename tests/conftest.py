"""Fixtures shared by the whole suite: real Redis, and one real anvil per test session.

The chain is an anvil node started once per session (once per pytest-xdist worker); every
test runs on a snapshot of it, reverted afterwards (`isolated_portal`), and talks to it through
the portal's own client over JSON-RPC, the code path production runs.
"""

import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta

import pytest
import redis
from django.conf import settings as django_settings
from eth_account.signers.local import LocalAccount

from accounts.models import Owner, OwnerToken, Robot
from accounts.services.api_tokens import owner_token_create
from accounts.services.owners import owner_create
from accounts.services.pairing import robot_pairing_answer, robot_pairing_request
from accounts.services.robots import robot_create
from chainworker import sender as chain_sender
from chainworker import services as chain_services
from chainworker.client import AuthROSChain
from portal.celery import app as celery_app
from portal.middleware import service_checks_forget
from smcrypto import sm2, sm4
from stack.anvil import AnvilProcess, start_anvil
from tests.support.anvil_rpc import anvil_rpc, genesis_hash
from tests.support.chain_setup import make_registered_owner
from tests.support.robot_setup import TEST_PASSWORD, PairedRobot, RobotSetup
from tests.support.tiers import spawning_allowed


@pytest.fixture(scope="session")
def redis_client() -> redis.Redis:
    client = redis.Redis.from_url(django_settings.REDIS_URL)
    try:
        client.ping()
    except redis.ConnectionError as exc:
        pytest.exit(f"the suite needs a real Redis at {django_settings.REDIS_URL}: {exc}", 1)
    return client


@pytest.fixture(scope="session")
def session_anvil() -> Iterator[AnvilProcess]:
    """The session's chain node (automine, anvil's own fees: a 1 gwei base fee)."""
    with spawning_allowed():
        node = start_anvil()
    with node:
        yield node


@pytest.fixture(autouse=True)
def isolated_portal(settings, tmp_path, redis_client, request, session_anvil) -> Iterator[str]:
    """Each test gets its own secrets, storage, Redis namespace and chain state: a snapshot of
    the session's anvil, reverted after the test (about 1 ms).

    Celery runs tasks eagerly (inline) unless the test is marked `worker`: those start real
    worker processes because they are about the queue.
    """
    url = session_anvil.url
    snapshot = anvil_rpc(url, "evm_snapshot")
    settings.SECRETS_DIR = tmp_path / "secrets"
    settings.MEDIA_ROOT = tmp_path / "media"
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": {
            "BACKEND": "sharing.storage.DurableFileSystemStorage",
            "OPTIONS": {"location": str(tmp_path / "media" / "envelopes")},
        },
    }
    settings.REDIS_KEY_PREFIX = f"authros-test-{uuid.uuid4().hex[:12]}"
    settings.CHAIN_RPC_URL = url
    settings.CHAIN_CONTRACT_ADDRESS = ""
    settings.CHAIN_OPERATOR_KEY = ""
    settings.AUTHROS_MASTER_KEY = ""
    settings.ANCHOR_MAX_WAIT = 0
    eager = request.node.get_closest_marker("worker") is None
    celery_app.conf.task_always_eager = eager
    celery_app.conf.task_eager_propagates = eager
    chain_services._clients.clear()
    # The service checks' verdict is kept per process: each test's secrets are its own.
    service_checks_forget()
    yield url
    service_checks_forget()
    chain_services._clients.clear()
    # Transactions a test left waiting (behind a nonce gap) would be mined into the next one.
    anvil_rpc(url, "anvil_dropAllTransactions")
    if anvil_rpc(url, "evm_revert", snapshot) is not True:
        raise AssertionError(f"anvil could not revert to the test's snapshot {snapshot}")
    for key in redis_client.scan_iter(f"{settings.REDIS_KEY_PREFIX}:*"):
        redis_client.delete(key)


@pytest.fixture
def deployed(db, isolated_portal) -> AuthROSChain:
    """The portal's own chain client, with the contract deployed and recorded."""
    chain_services.contract_deploy()
    return chain_services.chain_client()


@pytest.fixture
def make_owner(deployed, django_capture_on_commit_callbacks):
    """Create owners through the service; their on-chain registration runs inline."""

    def make(username: str | None = None, *, key: bytes | None = None) -> Owner:
        with django_capture_on_commit_callbacks(execute=True):
            owner = owner_create(
                username=username or f"owner-{uuid.uuid4().hex[:8]}",
                password=TEST_PASSWORD,
                sm4_key=key or sm4.generate_key(),
            )
        owner.refresh_from_db()
        return owner

    return make


@pytest.fixture
def operator() -> LocalAccount:
    return chain_services.operator_account()


@pytest.fixture
def chain(isolated_portal, redis_client, operator, settings) -> AuthROSChain:
    """A client of the test's chain with the AuthROS contract deployed by the operator."""
    client = AuthROSChain(
        isolated_portal,
        redis_client=redis_client,
        receipt_timeout=30,
        redis_prefix=settings.REDIS_KEY_PREFIX,
    )
    client.dev_faucet(operator.address, 10**21)
    client.deploy(operator)
    return client


@pytest.fixture
def registered_owner(chain, operator) -> LocalAccount:
    return make_registered_owner(chain, operator)


@pytest.fixture(scope="module")
def anvil() -> Iterator[AnvilProcess]:
    """A real anvil node for the module's integration tests (automine)."""
    with start_anvil() as node:
        yield node


@pytest.fixture
def records_mode(settings):
    """Anchor one record per slot (ANCHOR_MODE=records, the paper's interface): for tests of
    that mode's own behaviour (dataUploadBatch, write-once ids)."""
    settings.ANCHOR_MODE = "records"


@pytest.fixture
def worker_stack(tmp_path, settings, request):
    """Start real Celery workers and beat on an anvil of their own
    (tests.support.harness.WorkerStack): worker_stack(workers=N, block_time=None,
    env_overrides=None); stopped after the test. A failing test's report ends with the last
    lines of each process's log."""
    from tests.support.harness import WorkerStack

    stacks = []
    request.node.worker_stacks = stacks

    def make(
        *,
        workers: int,
        block_time: float | None = None,
        env_overrides: dict[str, str] | None = None,
    ) -> WorkerStack:
        stack = WorkerStack(tmp_path, block_time=block_time, env_overrides=env_overrides)
        stacks.append(stack)
        return stack.start(settings, workers=workers)

    yield make
    for stack in stacks:
        stack.stop()


@pytest.fixture
def on_commit(django_capture_on_commit_callbacks):
    """Run `action`; the work it queues on commit (chain work included) runs inline."""

    def run(action):
        with django_capture_on_commit_callbacks(execute=True):
            return action()

    return run


@pytest.fixture
def pair_robot(django_capture_on_commit_callbacks):
    """Pair a robot of `owner` as the agent pairs: its SM2 key pair made here, its request
    approved by the owner, its key registered on chain inline. `delivered=False`: the message
    queueing the key's registration is lost."""

    def pair(owner: Owner, *, delivered: bool = True) -> PairedRobot:
        private_key, public_key = sm2.generate_keypair()
        pairing, _secret = robot_pairing_request(
            name=f"robot-{uuid.uuid4().hex[:6]}", public_key=public_key
        )
        with django_capture_on_commit_callbacks(execute=delivered):
            pairing = robot_pairing_answer(
                owner=owner, code=pairing.code, approve=True, actor=owner.user
            )
        token = sm2.decrypt(private_key, pairing.token_sm2).decode("ascii")
        robot = Robot.objects.get(pk=pairing.robot_id)
        return PairedRobot(robot, token, (private_key, public_key))

    return pair


@pytest.fixture
def make_paired_robot(make_owner, pair_robot):
    """An owner (registered on chain) with one robot paired as the agent pairs
    (`pair_robot`); its envelopes are signed."""

    def make(username: str | None = None) -> RobotSetup:
        key = sm4.generate_key()
        owner = make_owner(username, key=key)
        paired = pair_robot(owner)
        return RobotSetup(owner, key, paired.robot, paired.token, paired.signing_key)

    return make


@pytest.fixture
def make_robot(make_owner):
    """An owner (registered on chain) with one robot, and the owner's SM4 key."""

    def make(username: str | None = None) -> RobotSetup:
        key = sm4.generate_key()
        owner = make_owner(username, key=key)
        robot, token = robot_create(owner=owner, name=f"robot-{uuid.uuid4().hex[:6]}")
        return RobotSetup(owner, key, robot, token)

    return make


# Tests that never touch the database: `make test` runs them once, not again on PostgreSQL.
_NO_DATABASE = (
    "tests/smcrypto/",
    "tests/contracts/",
    "tests/chainworker/test_client.py",
    "tests/chainworker/test_client_anvil.py",
    "tests/chainworker/test_codec.py",
    "tests/chainworker/test_rpc.py",
    "tests/chainworker/test_rpc_anvil.py",
    "tests/chainworker/test_sender.py",
    "tests/chainworker/test_sender_anvil.py",
    "tests/ros_agent/test_config.py",
    "tests/ros_agent/test_extractors.py",
    "tests/ros_agent/test_node.py",
    "tests/ros_agent/test_pipeline.py",
    "tests/ros_agent/test_ros2msg.py",
    "tests/ros_agent/test_sim.py",
    "tests/ros_agent/test_spool.py",
    "tests/ros_agent/test_uploader.py",
    "tests/ros_agent/test_wrapping.py",
    "tests/stack/test_stack_ros2.py",
    "tests/stack/test_webserver.py",
    "tests/packaging/test_deploy.py",
    "tests/packaging/test_imports.py",
)


# How much of each stack process's log a failing test's report shows.
_FAILURE_LOG_LINES = 60


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> pytest.TestReport:
    """A test that fails with worker stacks running reports the end of their processes' logs:
    the test's own output rarely says why a worker did not finish in time."""
    report = yield
    if report.when == "call" and report.failed:
        for stack in getattr(item, "worker_stacks", ()):
            for path in sorted(stack.logs.glob("*.log")):
                lines = path.read_text(errors="replace").splitlines()[-_FAILURE_LOG_LINES:]
                report.sections.append((f"end of {path.name}", "\n".join(lines)))
    return report


def pytest_configure(config: pytest.Config) -> None:
    """Passwords hashed in this process at few iterations (tests/support/hashers.py), before
    anything has hashed one (Django caches the hashers it built)."""
    django_settings.PASSWORD_HASHERS = [
        "tests.support.hashers.FewIterationsPBKDF2PasswordHasher",
        *django_settings.PASSWORD_HASHERS,
    ]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    root = str(config.rootpath) + "/"
    for item in items:
        if str(item.path).removeprefix(root).startswith(_NO_DATABASE):
            item.add_marker(pytest.mark.nodb)


@pytest.fixture
def make_owner_token(db):
    """An owner API token made through the service, and its key (shown once)."""

    def make(
        owner: Owner, *, scopes: tuple[str, ...] = ("read", "share"), days: int = 30
    ) -> tuple[OwnerToken, str]:
        return owner_token_create(
            owner=owner,
            name=f"script-{uuid.uuid4().hex[:6]}",
            scopes=list(scopes),
            expires_in=timedelta(days=days),
        )

    return make


@pytest.fixture
def eager_retries() -> Iterator[None]:
    """Tasks run inline, and a task's retries too: Celery retries an eager task inline only
    when its errors are not propagated to the caller (the suite propagates them)."""
    celery_app.conf.task_eager_propagates = False
    yield
    celery_app.conf.task_eager_propagates = True


@pytest.fixture
def blocks_lost(isolated_portal, monkeypatch, eager_retries):
    """`with blocks_lost(): ...`: the node loses every block mined inside, as one restarted
    from an older state does. The portal's nonce counters are then ahead of the node: a send
    meets the gap at its receipt wait (asked every 0.1 s here, not 5 s) and its task retries
    inline, as a worker would."""
    monkeypatch.setattr(chain_sender, "DROPPED_CHECK_INTERVAL", 0.1)

    @contextmanager
    def lose() -> Iterator[None]:
        snapshot = anvil_rpc(isolated_portal, "evm_snapshot")
        yield
        assert anvil_rpc(isolated_portal, "evm_revert", snapshot) is True

    return lose


@pytest.fixture
def fresh_chain(settings):
    """Point the portal at a new, empty chain (a reset): a node of its own, stopped afterwards,
    whose genesis differs from the one it replaces (anvil dates its genesis to the second)."""
    nodes: list[AnvilProcess] = []

    def reset() -> None:
        replaced = genesis_hash(settings.CHAIN_RPC_URL)
        while True:
            node = start_anvil()
            nodes.append(node)
            if genesis_hash(node.url) != replaced:
                break
            time.sleep(0.5)
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()

    yield reset
    for node in nodes:
        node.stop()
