"""The chain client against a real anvil node: several processes sending at once."""

import json
import logging
import multiprocessing
import threading
import uuid

import pytest
import redis
import requests
from eth_account import Account
from web3 import Web3

from chainworker.client import ANCHOR_ROOT_GAS, AuthROSChain
from chainworker.errors import (
    ChainUnavailable,
    ContractNotDeployed,
    InsufficientFunds,
    NodeRefused,
    TransactionDropped,
    TransactionReverted,
    TransactionTimeout,
)
from chainworker.rpc import rpc_session
from smcrypto import key_commitment, sm4
from stack.anvil import start_anvil
from tests.chain_setup import anchor_item, make_registered_owner

pytestmark = pytest.mark.process

SENDER_PROCESSES = 4
UPLOADS_PER_PROCESS = 15


def _deployed(url: str, redis_client: redis.Redis) -> tuple[AuthROSChain, Account]:
    client = AuthROSChain(url, redis_client=redis_client, receipt_timeout=30)
    operator = Account.create()
    assert client.dev_faucet(operator.address, 10**21)
    client.deploy(operator)
    return client, operator


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


def test_full_contract_flow_over_http(anvil, redis_client):
    client, operator = _deployed(anvil.url, redis_client)
    owner = make_registered_owner(client, operator)
    viewer = make_registered_owner(client, operator)
    item = anchor_item()
    result = client.data_upload(owner, item)
    assert result.events[0].name == "DataUploaded"
    assert client.data_query(item.record_id, owner=owner.address).digest == item.digest
    client.authority_grant(owner, viewer.address)
    assert client.has_access(owner.address, viewer.address)
    with pytest.raises(TransactionReverted) as refused:
        client.authority_grant(owner, viewer.address)
    assert refused.value.error_name == "AlreadyGranted"
    assert client.client_version.lower().startswith("anvil")


def test_concurrent_senders_in_several_processes_share_nonces(anvil, redis_client, settings):
    client, operator = _deployed(anvil.url, redis_client)
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


def test_receipt_timeout_when_nothing_is_mined(redis_client, tmp_path):
    with start_anvil() as node:
        client, operator = _deployed(node.url, redis_client)
        owner = make_registered_owner(client, operator)
        client.w3.provider.make_request("evm_setAutomine", [False])
        tx_hash = client.data_upload(owner, anchor_item(), wait=False)
        with pytest.raises(TransactionTimeout) as timed_out:
            client.wait_for_receipt(tx_hash, timeout=1)
        assert timed_out.value.tx_hash == tx_hash
        client.w3.provider.make_request("evm_mine", [])
        assert client.wait_for_receipt(tx_hash, timeout=5)["status"] == 1


def test_a_transaction_the_node_lost_or_holds_behind_a_nonce_gap_is_not_waited_for(
    redis_client,
):
    """A node that lost a sender's transaction (a restart without its pool, lost blocks) never
    mines the ones sent after it with the next nonces: the wait for their receipt ends at once,
    the nonce counter goes back to the node's count, and the next send is mined."""
    with start_anvil() as node:
        client, operator = _deployed(node.url, redis_client)
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


def test_confirmations_are_awaited(redis_client):
    with start_anvil(block_time=0.5) as node:
        client, operator = _deployed(node.url, redis_client)
        owner = make_registered_owner(client, operator)
        client.confirmations = 2
        result = client.data_upload(owner, anchor_item())
        assert client.latest_block() >= result.block_number + 2


def test_node_going_away_raises_chain_unavailable(redis_client):
    node = start_anvil()
    client, _operator = _deployed(node.url, redis_client)
    node.stop()
    with pytest.raises(ChainUnavailable):
        client.record_count()
    assert not client.is_connected()
    assert Web3.is_checksum_address(client.address)


def test_a_read_is_one_request_to_the_node(anvil, redis_client, monkeypatch):
    """web3 asks for the chain id before an eth_call; it is asked once per connection, so a
    view's rootOf or dataQuery is one HTTP request."""
    client, operator = _deployed(anvil.url, redis_client)
    owner = make_registered_owner(client, operator)
    item = anchor_item()
    client.data_upload(owner, item)
    client.anchor_root(owner, b"\x02" * 32, 5)
    client.data_query(
        item.record_id, owner=owner.address
    )  # the connection has asked its chain id by now
    methods = []
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        methods.append(kwargs["json"]["method"] if "json" in kwargs else kwargs.get("data"))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    assert client.data_query(item.record_id, owner=owner.address).digest == item.digest
    assert client.root_of(owner.address, b"\x01" * 32) is None
    anchored = client.root_of(owner.address, b"\x02" * 32)
    assert anchored.size == 5
    assert anchored.sender == owner.address
    assert len(methods) == 3
    assert all(b"eth_call" in m if isinstance(m, bytes) else m == "eth_call" for m in methods)


def test_the_views_read_at_an_address_without_code_is_contract_not_deployed(anvil, redis_client):
    """rootOf goes past web3's contract layer over HTTP: an empty answer (a reset chain) is
    still ContractNotDeployed, not a crash."""
    client = AuthROSChain(anvil.url, redis_client=redis_client)
    client.use_contract(Account.create().address)
    with pytest.raises(ContractNotDeployed):
        client.root_of(Account.create().address, b"\x01" * 32)


def test_the_nodes_session_reads_the_environment_once_and_is_shared_by_threads(
    anvil, redis_client, monkeypatch
):
    """Proxies and CA bundle from the environment when the client is made, not at every call
    (requests would read every variable again); one session for all of a process's threads."""
    monkeypatch.setenv("HTTP_PROXY", "http://proxy.invalid:3128")
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("REQUESTS_CA_BUNDLE", "/etc/ssl/certs/ca-certificates.crt")
    assert rpc_session("http://10.1.2.3:8545").proxies == {"http": "http://proxy.invalid:3128"}
    assert rpc_session("http://10.1.2.3:8545").verify == "/etc/ssl/certs/ca-certificates.crt"
    assert rpc_session(anvil.url).proxies == {}  # NO_PROXY names it

    client, operator = _deployed(anvil.url, redis_client)
    owner = make_registered_owner(client, operator)
    environment_read = []
    real_proxies = requests.utils.get_environ_proxies
    monkeypatch.setattr(
        requests.utils,
        "get_environ_proxies",
        lambda *a, **k: environment_read.append(a) or real_proxies(*a, **k),
    )
    sessions = set()
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        sessions.add(id(session))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    threads = [
        threading.Thread(target=client.root_of, args=(owner.address, b"\x01" * 32))
        for _ in range(4)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    client.anchor_root(owner, b"\x03" * 32, 2)
    assert client.last_root_of(owner.address) == b"\x03" * 32
    assert environment_read == []
    assert len(sessions) == 1


def _forked_reads(client: AuthROSChain, owner: str, answers) -> None:
    """In a forked child: the pool it inherited is empty, and its reads get their answers."""
    session = client.w3.provider._request_session_manager._explicit_session
    inherited = len(session.adapters["http://"].poolmanager.pools)
    results = [client.last_root_of(owner) for _ in range(30)]
    answers.put((inherited, {result.hex() for result in results}))


def test_a_process_forked_after_a_call_opens_its_own_connections(anvil, redis_client):
    """Celery's pool processes fork from a parent that checked the chain: a connection they
    shared would hand each of them the other's answers."""
    client, operator = _deployed(anvil.url, redis_client)
    owner = make_registered_owner(client, operator)
    client.anchor_root(owner, b"\x07" * 32, 3)
    session = client.w3.provider._request_session_manager._explicit_session
    assert client.last_root_of(owner.address) == b"\x07" * 32
    assert len(session.adapters["http://"].poolmanager.pools) == 1  # a connection is open
    context = multiprocessing.get_context("fork")
    answers = context.Queue()
    children = [
        context.Process(target=_forked_reads, args=(client, owner.address, answers))
        for _ in range(3)
    ]
    for child in children:
        child.start()
    # Meanwhile the parent reads too, on the connection it kept.
    assert {type(client.w3.eth.block_number) for _ in range(30)} == {int}
    outcomes = [answers.get(timeout=60) for _ in children]
    for child in children:
        child.join(timeout=60)
    assert outcomes == [(0, {"07" * 32})] * 3


def _methods_of(kwargs: dict) -> list[str] | str:
    """The JSON-RPC method of a request the client posts, or the methods of a batch."""
    body = kwargs["json"] if "json" in kwargs else json.loads(kwargs["data"])
    return [call["method"] for call in body] if isinstance(body, list) else body["method"]


def test_a_send_is_one_batch_the_nonce_the_transaction_and_its_receipt(
    anvil, redis_client, monkeypatch
):
    """A contract transaction to a real node is encoded and signed here: the estimate and the
    fees (this anvil charges for gas) in one batch, then the pending nonce, the raw transaction
    and its receipt, each one request past web3's formatters, the receipt formatted as web3
    formats it."""
    client, operator = _deployed(anvil.url, redis_client)
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


def test_a_refused_send_says_why(anvil, redis_client):
    """The node's refusals of a lean send: the contract's custom error with its arguments,
    and an account that cannot pay for gas (this anvil charges for gas)."""
    client, operator = _deployed(anvil.url, redis_client)
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


def test_a_receipt_the_node_cannot_tell_yet_is_asked_again(anvil, redis_client, monkeypatch):
    """A node that refuses a receipt for now (geth while it indexes transactions) is asked
    again at the next poll rather than failing the send."""
    client, operator = _deployed(anvil.url, redis_client)
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
