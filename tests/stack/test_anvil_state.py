"""`make run`'s anvil keeps its state so that a crash loses at most the last second: the state
is written every ANVIL_STATE_INTERVAL seconds, atomically, and a state file cut short (as
anvil's own in-place writer leaves it when killed mid-write) falls back to the previous copy."""

import json
import time
from pathlib import Path

import pytest
import redis
from eth_account import Account
from web3 import Web3

from chainworker.chain import AuthROSChain
from stack.anvil import AnvilProcess, start_anvil
from stack.run import ANVIL_STATE_INTERVAL
from tests.chainworker.test_chain_anvil import _item, _registered

pytestmark = pytest.mark.anvil


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
    node = start_anvil(state_path=state, state_interval=ANVIL_STATE_INTERVAL, zero_gas=True)
    try:
        client, operator = _deployed(node, redis_client)
        owner = _registered(client, operator)
        items = [_item() for _ in range(3)]
        client.data_upload_batch(owner, items)
        block = client.latest_block()
        kept = {n: client.w3.eth.get_block(n)["hash"] for n in range(block + 1)}
        balance = client.balance(owner.address)
        _wait_until_written(state, block)
    finally:
        _kill_9(node)

    with start_anvil(state_path=state, port=node.port, zero_gas=True) as again:
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
        assert all(restarted.data_query(item.record_id) is not None for item in items)
        assert restarted.balance(owner.address) == balance
        assert restarted.is_registered(owner.address)


def test_a_state_file_cut_short_falls_back_to_the_previous_copy(tmp_path, redis_client):
    state = tmp_path / "state.json"
    node = start_anvil(state_path=state, state_interval=ANVIL_STATE_INTERVAL, zero_gas=True)
    try:
        client, operator = _deployed(node, redis_client)
        deployed_at = client.latest_block()
        _wait_until_written(state, deployed_at)
        _registered(client, operator)  # more blocks: the copy above becomes the previous one
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
