"""Sending against a real anvil node: several processes sending at once, receipts that do
not come, transactions the node lost, confirmations, a send's requests and refusals."""

import json
import logging
import multiprocessing
import uuid

import pytest
import redis
import requests
from eth_account import Account

from chainworker.client import ANCHOR_ROOT_GAS, AuthROSChain
from chainworker.errors import (
    InsufficientFunds,
    NodeRefused,
    TransactionDropped,
    TransactionReverted,
    TransactionTimeout,
)
from smcrypto import key_commitment, sm4
from stack.anvil import start_anvil
from tests.support.chain_setup import anchor_item, make_registered_owner

pytestmark = pytest.mark.process

SENDER_PROCESSES = 4
UPLOADS_PER_PROCESS = 15


def _upload_from_another_process(url, redis_url, address, owner_key, count, queue) -> None:
    """Runs in a child process: its own client, the same EOA as the other children."""
    client = AuthROSChain(
        url, redis_client=redis.Redis.from_url(redis_url), contract_address=address
    )
    owner = Account.from_key(owner_key)
    sent = []
    refusals = _NonceRefusals()
    logging.getLogger("chainworker.sender").addHandler(refusals)
    try:
        for _ in range(count):
            item = anchor_item()
            sent.append((str(item.record_id), client.data_upload(owner, item, wait=False)))
        for _, tx_hash in sent:
            client.wait_for_receipt(tx_hash)
        queue.put(("ok", [record_id for record_id, _ in sent], refusals.count))
    except Exception as exc:  # report any failure to the parent, whatever it is
        queue.put(("error", f"{type(exc).__name__}: {exc}", refusals.count))


class _NonceRefusals(logging.Handler):
    """Counts the node's refusals of a nonce, which the client survives by resyncing: with
    the shared counter and lock there should be none at all."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.getMessage().startswith("nonce "):
            self.count += 1


def test_concurrent_senders_in_several_processes_share_nonces(
    deploy_on, anvil, redis_client, settings
):
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    workers = [
        context.Process(
            target=_upload_from_another_process,
            args=(
                anvil.url,
                settings.REDIS_URL,
                client.address,
                owner.key.hex(),
                UPLOADS_PER_PROCESS,
                queue,
            ),
        )
        for _ in range(SENDER_PROCESSES)
    ]
    for worker in workers:
        worker.start()
    outcomes = [queue.get(timeout=120) for _ in workers]
    for worker in workers:
        worker.join(timeout=30)
    errors = [detail for status, detail, _ in outcomes if status == "error"]
    assert errors == []
    assert [refusals for _, _, refusals in outcomes] == [0] * SENDER_PROCESSES
    record_ids = [record_id for _, ids, _ in outcomes for record_id in ids]
    assert len(set(record_ids)) == SENDER_PROCESSES * UPLOADS_PER_PROCESS
    assert client.record_count() == SENDER_PROCESSES * UPLOADS_PER_PROCESS
    assert all(
        client.data_query(record_id, owner=owner.address) is not None for record_id in record_ids
    )
    uploads = client.events(names=["DataUploaded"])
    assert sorted(str(e.args["id"][:16].hex()) for e in uploads) == sorted(
        uuid.UUID(r).hex for r in record_ids
    )


def test_receipt_timeout_when_nothing_is_mined(deploy_on, redis_client, tmp_path):
    with start_anvil() as node:
        client, operator = deploy_on(node.url)
        owner = make_registered_owner(client, operator)
        client.w3.provider.make_request("evm_setAutomine", [False])
        tx_hash = client.data_upload(owner, anchor_item(), wait=False)
        with pytest.raises(TransactionTimeout) as timed_out:
            client.wait_for_receipt(tx_hash, timeout=1)
        assert timed_out.value.tx_hash == tx_hash
        client.w3.provider.make_request("evm_mine", [])
        assert client.wait_for_receipt(tx_hash, timeout=5)["status"] == 1


def test_a_transaction_the_node_lost_or_holds_behind_a_nonce_gap_is_not_waited_for(
    deploy_on,
    redis_client,
):
    """A node that lost a sender's transaction (a restart without its pool, lost blocks) never
    mines the ones sent after it with the next nonces: the wait for their receipt ends at once,
    the nonce counter goes back to the node's count, and the next send is mined."""
    with start_anvil() as node:
        client, operator = deploy_on(node.url)
        owner = make_registered_owner(client, operator)
        client.w3.provider.make_request("evm_setAutomine", [False])
        lost = client.data_upload(owner, anchor_item(), wait=False)
        ready_nonce = client.w3.eth.get_transaction_count(owner.address)
        assert client.transaction_pending(lost)
        client.w3.provider.make_request("anvil_dropTransaction", [lost])
        client.w3.provider.make_request("evm_setAutomine", [True])
        with pytest.raises(TransactionDropped, match="does not hold it"):
            client.wait_for_receipt(lost)
        # Our counter still counts the lost one: the next send waits behind the gap.
        gapped = client.data_upload(owner, anchor_item(), wait=False)
        assert client.w3.eth.get_transaction(gapped)["nonce"] == ready_nonce + 1
        assert not client.transaction_pending(gapped)
        with pytest.raises(TransactionDropped, match="waits behind a gap"):
            client.wait_for_receipt(gapped)
        item = anchor_item()
        receipt = client.wait_for_receipt(client.data_upload(owner, item, wait=False))
        assert client.w3.eth.get_transaction(receipt["transactionHash"])["nonce"] == ready_nonce
        assert client.data_query(item.record_id, owner=owner.address) is not None


def test_confirmations_are_awaited(deploy_on, redis_client):
    with start_anvil(block_time=0.5) as node:
        client, operator = deploy_on(node.url)
        owner = make_registered_owner(client, operator)
        client.confirmations = 2
        result = client.data_upload(owner, anchor_item())
        assert client.latest_block() >= result.block_number + 2


def _methods_of(kwargs: dict) -> list[str] | str:
    """The JSON-RPC method of a request the client posts, or the methods of a batch."""
    body = kwargs["json"] if "json" in kwargs else json.loads(kwargs["data"])
    return [call["method"] for call in body] if isinstance(body, list) else body["method"]


def test_a_send_is_one_batch_the_nonce_the_transaction_and_its_receipt(
    deploy_on, anvil, redis_client, monkeypatch
):
    """A contract transaction to a real node is encoded and signed here: the estimate and the
    fees (this anvil charges for gas) in one batch, then the pending nonce, the raw transaction
    and its receipt, each one request past web3's formatters, the receipt formatted as web3
    formats it."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    methods = []
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        methods.append(_methods_of(kwargs))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    result = client.anchor_root(owner, b"\x05" * 32, 9)
    assert methods[:3] == [
        ["eth_getBlockByNumber", "eth_gasPrice", "eth_maxPriorityFeePerGas", "eth_estimateGas"],
        "eth_getTransactionCount",
        "eth_sendRawTransaction",
    ]
    assert methods[3:]
    assert set(methods[3:]) == {"eth_getTransactionReceipt"}
    (event,) = result.events
    assert event.name == "RootAnchored"
    assert event.args["size"] == 9
    assert event.tx_hash == result.tx_hash
    assert client.root_of(owner.address, b"\x05" * 32).block_number == result.block_number
    assert 0 < result.gas_used < ANCHOR_ROOT_GAS


def test_a_refused_send_says_why(deploy_on, anvil, redis_client):
    """The node's refusals of a lean send: the contract's custom error with its arguments,
    and an account that cannot pay for gas (this anvil charges for gas)."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    first = client.anchor_root(owner, b"\x01" * 32, 1)
    assert first.events[0].args["prevRoot"] == bytes(32)
    with pytest.raises(TransactionReverted) as wrong:
        client.anchor_root(owner, b"\x02" * 32, 1, prev_root=b"\x09" * 32)
    assert wrong.value.error_name == "WrongPrevRoot"
    assert wrong.value.error_args == {"expected": b"\x01" * 32, "given": b"\x09" * 32}
    with pytest.raises(TransactionReverted) as again:
        client.anchor_root(owner, b"\x01" * 32, 1, prev_root=b"\x01" * 32)
    assert again.value.error_name == "RootExists"
    assert client.last_root_of(owner.address) == b"\x01" * 32  # nothing else landed

    poor = Account.create()
    client.enroll(operator, poor.address)
    with pytest.raises(InsufficientFunds):
        client.register(poor, key_commitment(poor.address, sm4.generate_key()))
    assert not client.is_registered(poor.address)


def test_a_receipt_the_node_cannot_tell_yet_is_asked_again(
    deploy_on, anvil, redis_client, monkeypatch
):
    """A node that refuses a receipt for now (geth while it indexes transactions) is asked
    again at the next poll rather than failing the send."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    tx_hash = client.anchor_root(owner, b"\x06" * 32, 3, wait=False)
    refusals = []
    lean = client.rpc.request

    def indexing_at_first(method, params, *, label):
        if method == "eth_getTransactionReceipt" and len(refusals) < 2:
            refusals.append(method)
            raise NodeRefused(label, "transaction indexing is in progress")
        return lean(method, params, label=label)

    monkeypatch.setattr(client.rpc, "request", indexing_at_first)
    client.poll_interval = 0.01
    receipt = client.wait_for_receipt(tx_hash, timeout=10)
    assert len(refusals) == 2
    assert receipt["status"] == 1
    assert "0x" + bytes(receipt["transactionHash"]).hex() == tx_hash


def test_a_deploy_and_a_transfer_are_built_as_a_contract_call_is(deploy_on, anvil, monkeypatch):
    """One builder for every send: a deployment's estimate and fees in one batch, a transfer's
    fees in one (its gas is known), each then the nonce, the raw transaction and its receipt."""
    client, operator = deploy_on(anvil.url)
    methods = []
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        methods.append(_methods_of(kwargs))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    deployed = client.deploy(operator)
    assert methods[:3] == [
        ["eth_getBlockByNumber", "eth_gasPrice", "eth_maxPriorityFeePerGas", "eth_estimateGas"],
        "eth_getTransactionCount",
        "eth_sendRawTransaction",
    ]
    assert client.has_code(client.address)
    assert client.admin() == operator.address
    assert deployed.block_number > 0
    assert client.record_count() == 0
    methods.clear()
    payee = Account.create()
    client.transfer(operator, payee.address, 12345)
    assert methods[:3] == [
        ["eth_getBlockByNumber", "eth_gasPrice", "eth_maxPriorityFeePerGas"],
        "eth_getTransactionCount",
        "eth_sendRawTransaction",
    ]
    assert client.balance(payee.address) == 12345


def test_a_transaction_that_reverts_when_mined_is_named_by_its_replay(deploy_on, anvil):
    """Sent without an estimate, a root the chain refuses is mined and fails: the wait replays
    it as an eth_call at its parent block and names the contract's error."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    client.anchor_root(owner, b"\x01" * 32, 1)
    tx_hash = client.anchor_root(
        owner, b"\x02" * 32, 1, prev_root=b"\x09" * 32, wait=False, estimate=False
    )
    with pytest.raises(TransactionReverted) as refused:
        client.wait_for_receipt(tx_hash, function="anchorRoot")
    assert refused.value.error_name == "WrongPrevRoot"
    assert refused.value.error_args == {"expected": b"\x01" * 32, "given": b"\x09" * 32}
    assert refused.value.tx_hash == tx_hash
    assert refused.value.function == "anchorRoot"
    assert client.last_root_of(owner.address) == b"\x01" * 32
