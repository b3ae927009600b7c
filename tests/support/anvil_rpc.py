"""JSON-RPC calls to a test's anvil node: anvil's own test methods (snapshots, time, mining)
and the genesis block that tells one chain from another."""

import requests


def anvil_rpc(url: str, method: str, *params: object) -> object:
    """One JSON-RPC call to a test node (snapshots, time, mining); its result."""
    answer = requests.post(
        url, json={"jsonrpc": "2.0", "id": 1, "method": method, "params": list(params)}, timeout=30
    ).json()
    if "error" in answer:
        raise AssertionError(f"{method}: anvil refused: {answer['error']}")
    return answer["result"]


def chain_time_travel(url: str, timestamp: int) -> None:
    """Mine the next block at `timestamp` (seconds), as the node's clock would later."""
    anvil_rpc(url, "evm_setNextBlockTimestamp", timestamp)
    anvil_rpc(url, "evm_mine")


def blocks_mine(url: str, count: int) -> None:
    anvil_rpc(url, "anvil_mine", hex(count))


def genesis_hash(url: str) -> str:
    return anvil_rpc(url, "eth_getBlockByNumber", "0x0", False)["hash"]
