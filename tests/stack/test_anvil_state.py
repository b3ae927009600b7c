"""`make run`'s anvil keeps its state so that a crash loses at most the last second: the state
is written every ANVIL_STATE_INTERVAL seconds, atomically, and a state file cut short (as
anvil's own in-place writer leaves it when killed mid-write) falls back to the previous copy."""

import gzip
import http.server
import json
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import redis
from eth_account import Account
from web3 import Web3
from web3.exceptions import Web3RPCError

from chainworker.client import AuthROSChain
from stack.anvil import KEPT_STATES, AnvilProcess, StateKeeper, start_anvil
from stack.run import ANVIL_STATE_INTERVAL, ANVIL_TRANSACTION_BLOCKS
from tests.support.chain_setup import anchor_item, make_registered_owner

pytestmark = pytest.mark.process


def _deployed(node: AnvilProcess, redis_client: redis.Redis) -> tuple[AuthROSChain, Account]:
    client = AuthROSChain(
        node.url, redis_client=redis_client, receipt_timeout=30, redis_prefix=_prefix()
    )
    operator = Account.create()
    assert client.dev_faucet(operator.address, 10**21)
    client.deploy(operator)
    return client, operator


def _prefix() -> str:
    return f"authros-test-state-{time.monotonic_ns()}"


def _written_block(path: Path) -> int:
    """The best block of the state file as it is now (-1 while there is none)."""
    try:
        return int(str(json.loads(path.read_bytes())["best_block_number"]), 0)
    except (OSError, ValueError, KeyError):
        return -1


def _wait_until_written(path: Path, block: int, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while _written_block(path) < block:
        assert time.monotonic() < deadline, f"{path} never reached block {block}"
        time.sleep(0.1)


def _kill_9(node: AnvilProcess) -> None:
    node.process.kill()
    node.process.wait(timeout=10)
    node.stop()  # nothing left to write: the keeper sees the node gone


def test_make_run_writes_the_state_every_second():
    assert ANVIL_STATE_INTERVAL == 1


def test_a_kill_9_keeps_everything_written_before_the_last_second(tmp_path, redis_client):
    state = tmp_path / "state.json"
    node = start_anvil(
        state_path=state,
        state_interval=ANVIL_STATE_INTERVAL,
        transaction_blocks=ANVIL_TRANSACTION_BLOCKS,
        zero_gas=True,
    )
    try:
        client, operator = _deployed(node, redis_client)
        owner = make_registered_owner(client, operator)
        items = [anchor_item() for _ in range(3)]
        client.data_upload_batch(owner, items)
        block = client.latest_block()
        kept = {n: client.w3.eth.get_block(n)["hash"] for n in range(block + 1)}
        balance = client.balance(owner.address)
        _wait_until_written(state, block)
    finally:
        _kill_9(node)

    with start_anvil(
        state_path=state,
        port=node.port,
        transaction_blocks=ANVIL_TRANSACTION_BLOCKS,
        zero_gas=True,
    ) as again:
        w3 = Web3(Web3.HTTPProvider(again.url))
        assert w3.eth.block_number >= block
        assert {n: w3.eth.get_block(n)["hash"] for n in kept} == kept  # same blocks, same genesis
        restarted = AuthROSChain(
            again.url,
            redis_client=redis_client,
            contract_address=client.address,
            redis_prefix=_prefix(),
        )
        assert restarted.has_code(client.address)
        assert restarted.record_count() == len(items)
        assert all(
            restarted.data_query(item.record_id, owner=owner.address) is not None for item in items
        )
        assert restarted.balance(owner.address) == balance
        assert restarted.is_registered(owner.address)


def test_a_state_file_cut_short_falls_back_to_the_previous_copy(tmp_path, redis_client):
    state = tmp_path / "state.json"
    node = start_anvil(state_path=state, state_interval=ANVIL_STATE_INTERVAL, zero_gas=True)
    try:
        client, operator = _deployed(node, redis_client)
        deployed_at = client.latest_block()
        _wait_until_written(state, deployed_at)
        # More blocks: the copy above becomes the previous one.
        make_registered_owner(client, operator)
        _wait_until_written(state, client.latest_block())
    finally:
        _kill_9(node)
    # What a kill -9 in the middle of anvil's own (in-place) write leaves behind.
    whole = state.read_bytes()
    state.write_bytes(whole[: len(whole) // 2])

    with start_anvil(state_path=state, port=node.port, zero_gas=True) as again:
        restarted = AuthROSChain(
            again.url,
            redis_client=redis_client,
            contract_address=client.address,
            redis_prefix=_prefix(),
        )
        assert restarted.latest_block() >= deployed_at
        assert restarted.has_code(client.address)
    assert (tmp_path / "state.json.bad").read_bytes() == whole[: len(whole) // 2]
    assert _written_block(state) >= deployed_at  # written again, whole, on the way out


def _rpc(url: str, method: str) -> dict:
    w3 = Web3(Web3.HTTPProvider(url))
    return w3.provider.make_request(method, [])


def _send(w3: Web3, count: int) -> list[bytes]:
    sender, receiver = w3.eth.accounts[:2]
    return [
        w3.eth.wait_for_transaction_receipt(
            w3.eth.send_transaction({"from": sender, "to": receiver, "value": 1, "gasPrice": 0})
        )["transactionHash"]
        for _ in range(count)
    ]


def test_the_state_is_written_as_the_node_gives_it_and_only_when_it_changed(tmp_path, monkeypatch):
    monkeypatch.setattr("stack.anvil._CHUNK", 7)  # odd: chunks split hex digits and gzip blocks
    state = tmp_path / "state.json"
    previous = tmp_path / "state.json.prev"
    with start_anvil(state_path=state, state_interval=3600, zero_gas=True) as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        _send(w3, 3)
        assert node.keeper.write()
        dumped = _rpc(node.url, "anvil_dumpState")["result"]
        assert state.read_bytes() == gzip.decompress(bytes.fromhex(dumped.removeprefix("0x")))
        first = state.stat()

        assert node.keeper.write()  # nothing happened on the chain: the file stays as it is
        assert state.stat().st_ino == first.st_ino
        assert state.stat().st_mtime_ns == first.st_mtime_ns

        _send(w3, 1)
        written = state.read_bytes()
        assert node.keeper.write()
        assert state.stat().st_ino != first.st_ino
        assert previous.read_bytes() == written  # the copy before stays as .prev
        assert _written_block(state) == w3.eth.block_number
        assert not (tmp_path / "state.json.partial").exists()


class _Answer(http.server.BaseHTTPRequestHandler):
    body = b""

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["Content-Length"]))
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.end_headers()
        self.wfile.write(self.body)

    def log_message(self, *args: object) -> None:
        pass


@pytest.mark.parametrize(
    "body",
    [
        b'{"jsonrpc":"2.0","id":1,"error":{"code":-32601,"message":"Method not found"}}',
        # a state cut short on the way: the gzip stream never ends
        b'{"jsonrpc":"2.0","id":1,"result":"0x'
        + gzip.compress(b'{"block":{}}' * 100)[:40].hex().encode()
        + b'"}',
        b'{"jsonrpc":"2.0","id":1,"result":"0xnot hex"}',
        b"<html>a proxy's error page</html>",
    ],
    ids=["error", "cut-short", "not-hex", "not-json-rpc"],
)
def test_an_answer_that_is_not_a_whole_state_replaces_nothing(tmp_path, body):
    state = tmp_path / "state.json"
    state.write_bytes(b'{"best_block_number":"0x7"}')
    handler = type("Answer", (_Answer,), {"body": body})
    server = http.server.HTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        node = SimpleNamespace(
            url=f"http://127.0.0.1:{server.server_port}", port=server.server_port
        )
        assert StateKeeper(node, state, interval=3600).write() is False
    finally:
        server.shutdown()
        server.server_close()
    assert state.read_bytes() == b'{"best_block_number":"0x7"}'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]


def test_make_runs_node_drops_old_transactions_and_keeps_all_state(tmp_path):
    """The node's memory and state file grow by block headers, not by transactions; the
    state itself (balances, code, storage) is whole, before and after a restart."""
    state = tmp_path / "state.json"
    with start_anvil(
        state_path=state, state_interval=3600, transaction_blocks=4, zero_gas=True
    ) as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        receiver = w3.eth.accounts[1]
        before = w3.eth.get_balance(receiver)
        sent = _send(w3, 12)
        assert w3.eth.get_transaction_receipt(sent[-1])["status"] == 1  # recent: kept
        assert w3.eth.get_block(2)["transactions"] == []  # old: dropped
        assert w3.eth.get_balance(receiver) == before + 12
        node.keeper.write()
    assert len(json.loads(state.read_bytes())["transactions"]) <= 4
    with start_anvil(state_path=state, transaction_blocks=4, zero_gas=True) as again:
        w3 = Web3(Web3.HTTPProvider(again.url))
        assert w3.eth.get_balance(receiver) == before + 12
        assert w3.eth.block_number == 12


def test_make_runs_node_keeps_recent_states_in_memory_and_no_older_ones(tmp_path):
    """Older states are dropped, not written under ~/.foundry/anvil/tmp (tens of GB in a day of
    uploads, left behind when the node stops); the latest ones serve a failed transaction's
    replay at its parent block."""
    with start_anvil(transaction_blocks=4, zero_gas=True) as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        receiver = w3.eth.accounts[1]
        before = w3.eth.get_balance(receiver)
        _send(w3, KEPT_STATES + 16)
        latest = w3.eth.block_number
        assert w3.eth.get_balance(receiver, block_identifier=latest - 1) == before + latest - 1
        with pytest.raises(Web3RPCError):
            w3.eth.get_balance(receiver, block_identifier=1)
