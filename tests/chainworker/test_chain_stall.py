"""A stalled chain (it accepts transactions and mines nothing) pauses sending without using up
attempts, raises one operator alert and says so in `chain_status` and the admin; once blocks
move again everything waiting is anchored exactly once and the alert is resolved. Against a
real anvil, in automine mode (`make run`'s) and with interval mining."""

import time
from collections.abc import Callable, Iterator

import pytest
import requests
from django.core.management import call_command
from django.urls import reverse
from django.utils import timezone

from accounts.models import ChainActivity
from chainworker import services as chain_services
from chainworker.errors import TransactionTimeout
from chainworker.models import OperatorAlert
from chainworker.services import CHAIN_STALLED_ALERT, chain_stall_forget, chain_stalled
from chainworker.work import ChainWorkNotReady
from sharing.models import Record
from sharing.services import anchoring
from sharing.services.uploads import record_create
from stack.anvil import AnvilProcess, start_anvil
from tests.support.anchoring_checks import assert_anchored_exactly_once, records_on_chain

pytestmark = [pytest.mark.django_db, pytest.mark.process]

STALL_AFTER = 1.5


@pytest.fixture
def node_options() -> dict[str, object]:
    return {}


@pytest.fixture
def node(settings, isolated_portal, node_options) -> Iterator[AnvilProcess]:
    """The portal's chain is a real anvil (zero gas, as `make run` starts it), with short
    receipt and stall timeouts."""
    with start_anvil(zero_gas=True, **node_options) as anvil:
        settings.CHAIN_RPC_URL = anvil.url
        settings.CHAIN_RECEIPT_TIMEOUT = 2 * STALL_AFTER
        settings.CHAIN_STALL_AFTER = STALL_AFTER
        chain_services._clients.clear()
        yield anvil
        chain_services._clients.clear()


@pytest.fixture
def deployed(db, node):
    """The contract deployed on the anvil node (a node of its own, not the session's)."""
    chain_services.contract_deploy()
    return chain_services.chain_client()


def rpc(node: AnvilProcess, method: str, *params: object) -> object:
    answer = requests.post(
        node.url,
        json={"jsonrpc": "2.0", "id": 1, "method": method, "params": list(params)},
        timeout=30,
    ).json()
    assert "error" not in answer, answer
    return answer["result"]


def wait_until(condition: Callable[[], bool], what: str, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def head_older_than_stall(node_client) -> bool:
    _number, timestamp = node_client.head()
    return timezone.now().timestamp() - timestamp > STALL_AFTER + 0.5


def automine_resume(node: AnvilProcess, node_client) -> None:
    """Automine back on: anvil mines what waits in its pool, though not always before the
    call returns; wait for the pool to empty."""
    rpc(node, "evm_setAutomine", True)
    wait_until(lambda: node_client.pending_transaction_count() == 0, "the pool to be mined")


def stall_alerts() -> list[OperatorAlert]:
    return list(OperatorAlert.objects.filter(kind=CHAIN_STALLED_ALERT))


def test_an_idle_automine_chain_is_not_stalled_but_one_that_mines_nothing_is(deployed, node):
    wait_until(lambda: head_older_than_stall(deployed), "the chain to be idle a while")
    assert not chain_stalled().stalled  # no block for a while, but nothing waits: idle

    rpc(node, "evm_setAutomine", False)
    sender = deployed.w3.eth.accounts[0]
    deployed.w3.eth.send_transaction({"from": sender, "to": sender, "value": 1, "gasPrice": 0})
    # It just arrived on a long idle chain: not a stall yet.
    first = chain_stalled()
    assert (first.stalled, first.waiting) == (False, 1)
    wait_until(lambda: chain_stalled().stalled, "the stall to be seen")
    assert "transaction(s) wait" in chain_stalled().reason

    automine_resume(node, deployed)  # mines what waits
    assert not chain_stalled().stalled


def test_records_wait_on_a_stalled_chain_without_using_attempts(
    deployed, node, make_robot, capsys, admin_client
):
    setup = make_robot("alice")
    wait_until(lambda: head_older_than_stall(deployed), "the chain to be idle a while")
    rpc(node, "evm_setAutomine", False)  # accepts transactions, mines nothing
    records = [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in (1, 2, 3)]

    # The batch is sent and its receipt never comes: the chain is stalled, the attempt given back.
    with pytest.raises(TransactionTimeout):
        anchoring.records_anchor(owner_id=setup.owner.pk)
    # Every sender now pauses before sending anything.
    with pytest.raises(ChainWorkNotReady, match="sending is paused, the chain is stalled"):
        anchoring.records_anchor(owner_id=setup.owner.pk)
    chain_stall_forget()  # asked afresh, the chain is still stalled
    with pytest.raises(ChainWorkNotReady, match="no new block for"):
        anchoring.records_anchor(owner_id=setup.owner.pk)
    states = set(Record.objects.values_list("status", "anchor_attempts"))
    assert states == {(Record.Status.PENDING, 0)}
    [alert] = stall_alerts()
    assert alert.resolved_at is None
    assert alert.detail["waiting"] == 1

    call_command("chain_status")
    out, err = capsys.readouterr()
    assert "chain stalled: yes" in out
    assert "chain stalled: no new block for" in err
    page = admin_client.get(reverse("admin:chain-status"))
    assert b"chain stalled: no new block for" in page.content

    automine_resume(node, deployed)  # the node mines again (what waited first)
    chain_stall_forget()
    anchoring.records_anchor(owner_id=setup.owner.pk)

    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}
    assert_anchored_exactly_once(deployed)  # no second copy sent
    assert records_on_chain(deployed) == len(records)
    anchored = ChainActivity.objects.filter(kind=ChainActivity.Kind.ANCHORED)
    assert list(anchored.values_list("record_count", flat=True)) == [len(records)]
    [alert] = stall_alerts()
    assert alert.resolved_at is not None
    call_command("chain_status")
    out, err = capsys.readouterr()
    assert "chain stalled: no" in out
    assert "chain stalled:" not in err


@pytest.mark.parametrize("node_options", [{"block_time": 1}])
def test_with_interval_mining_no_block_for_a_while_is_a_stall_even_when_idle(
    deployed, node, make_robot, settings
):
    settings.CHAIN_BLOCK_TIME = 1
    setup = make_robot("alice")
    wait_until(lambda: deployed.head()[0] >= 2, "interval mining to make blocks")
    assert not chain_stalled().stalled  # empty blocks keep coming

    rpc(node, "evm_setIntervalMining", 0)  # the validators stop
    wait_until(lambda: chain_stalled().stalled, "the stall to be seen")
    assert "a block every 1 s is expected" in chain_stalled().reason
    record = record_create(robot=setup.robot, data=setup.seal(1))
    chain_stall_forget()
    with pytest.raises(ChainWorkNotReady, match="the chain is stalled"):
        anchoring.records_anchor(owner_id=setup.owner.pk)
    record.refresh_from_db()
    assert (record.status, record.anchor_attempts) == (Record.Status.PENDING, 0)
    assert len(stall_alerts()) == 1

    rpc(node, "evm_setIntervalMining", 1)
    wait_until(lambda: not chain_stalled().stalled, "blocks to move again")
    chain_stall_forget()
    anchoring.records_anchor(owner_id=setup.owner.pk)
    record.refresh_from_db()
    assert (record.status, record.anchor_attempts) == (Record.Status.ANCHORED, 1)
    [alert] = stall_alerts()
    assert alert.resolved_at is not None
