"""AuthROS contract fixtures: plain web3 on the session's anvil (its unlocked dev accounts),
no portal code."""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from eth_abi import decode as abi_decode
from eth_typing import ChecksumAddress
from eth_utils import abi_to_signature, get_abi_input_types, keccak, to_checksum_address
from web3 import Web3
from web3.contract import Contract
from web3.contract.contract import ContractFunction
from web3.exceptions import ContractLogicError
from web3.logs import STRICT
from web3.types import TxParams, TxReceipt

REPO_ROOT = Path(__file__).resolve().parents[2]
ARTIFACT_PATH = REPO_ROOT / "contracts" / "build" / "AuthROS.json"

RevertExpectation = Callable[..., AbstractContextManager[None]]
RecordFields = tuple[bytes, bytes, int, bytes]


def error_decoders(abi: list[dict[str, Any]]) -> dict[bytes, tuple[str, list[str]]]:
    """Selector -> (error name, argument types) for every custom error in the ABI."""
    return {
        keccak(text=abi_to_signature(entry))[:4]: (entry["name"], get_abi_input_types(entry))
        for entry in abi
        if entry["type"] == "error"
    }


def revert_data(exc: BaseException) -> bytes | None:
    """The raw revert data (selector + arguments) carried by a web3 exception, if any.

    Over JSON-RPC (anvil, geth) web3 raises ContractCustomError with the data as hex, on the
    exception itself or on the one it replaced.
    """
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, ContractLogicError) and str(seen.data).startswith("0x"):
            return bytes.fromhex(str(seen.data)[2:])
        seen = seen.__cause__ or seen.__context__
    return None


def decode_revert(abi: list[dict[str, Any]], exc: BaseException) -> tuple[str, tuple[Any, ...]]:
    """(error name, arguments) of a custom-error revert; addresses come back checksummed."""
    data = revert_data(exc)
    if data is None or len(data) < 4:
        raise AssertionError(f"no custom error data in {exc!r}")
    decoders = error_decoders(abi)
    if data[:4] not in decoders:
        raise AssertionError(f"unknown error selector 0x{data[:4].hex()} in {exc!r}")
    name, types = decoders[data[:4]]
    values = abi_decode(types, data[4:])
    return name, tuple(
        to_checksum_address(value) if kind == "address" else value
        for kind, value in zip(types, values, strict=True)
    )


def commitment_for(eoa: str) -> bytes:
    """A distinct nonzero 32-byte stand-in for the SM3 key commitment of an EOA."""
    return keccak(text=f"test-commitment/{eoa}")


def record_fields(n: int) -> RecordFields:
    """(id, digest, time, dataType) of the n-th test record, shaped as the portal sends them."""
    record_id = uuid.UUID(int=n + 1).bytes.ljust(32, b"\0")  # UUID left-aligned in bytes32
    digest = keccak(text=f"envelope-{n}")  # stand-in for SM3(envelope)
    data_type = b"nav_msgs/Odometry".ljust(32, b"\0")
    return record_id, digest, 1_700_000_000 + n, data_type


@pytest.fixture(scope="session")
def artifact() -> dict[str, Any]:
    return json.loads(ARTIFACT_PATH.read_text())


@pytest.fixture(scope="session")
def record() -> Callable[[int], RecordFields]:
    return record_fields


@dataclass(frozen=True)
class DeployedChain:
    w3: Web3
    authros: Contract


def send_transaction(
    w3: Web3, call: ContractFunction, sender: str, gas: int | None = None
) -> TxReceipt:
    """Send a contract call as a transaction from `sender`; return its successful receipt.

    Without `gas`, the node estimates it first.
    """
    transaction: TxParams = {"from": sender} if gas is None else {"from": sender, "gas": gas}
    receipt = w3.eth.wait_for_transaction_receipt(call.transact(transaction))
    assert receipt["status"] == 1
    return receipt


@pytest.fixture(scope="session")
def deployment(artifact: dict[str, Any], session_anvil) -> DeployedChain:
    """The contract and its accounts set up once on the session's anvil, before the first
    test that asks for them takes its snapshot: every test starts from this common state.
    Accounts: 0 admin, 1-3 registered (alice, bob, carol), 4 enrolled only, 5-9 unknown.
    """
    w3 = Web3(Web3.HTTPProvider(session_anvil.url))
    admin = w3.eth.accounts[0]
    factory = w3.eth.contract(abi=artifact["abi"], bytecode=artifact["bytecode"])
    receipt = w3.eth.wait_for_transaction_receipt(factory.constructor().transact({"from": admin}))
    authros = w3.eth.contract(address=receipt["contractAddress"], abi=artifact["abi"])
    for eoa in w3.eth.accounts[1:5]:
        send_transaction(w3, authros.functions.enroll(eoa), admin)
    for eoa in w3.eth.accounts[1:4]:
        send_transaction(w3, authros.functions.register(commitment_for(eoa)), eoa)
    return DeployedChain(w3=w3, authros=authros)


@pytest.fixture
def w3(deployment: DeployedChain) -> Web3:
    """The session chain, rolled back to the common state after the test (isolated_portal)."""
    return deployment.w3


@pytest.fixture
def authros(w3: Web3, deployment: DeployedChain) -> Contract:
    return deployment.authros


@pytest.fixture
def admin(w3: Web3) -> ChecksumAddress:
    return w3.eth.accounts[0]


@pytest.fixture
def alice(w3: Web3) -> ChecksumAddress:
    return w3.eth.accounts[1]


@pytest.fixture
def bob(w3: Web3) -> ChecksumAddress:
    return w3.eth.accounts[2]


@pytest.fixture
def carol(w3: Web3) -> ChecksumAddress:
    return w3.eth.accounts[3]


@pytest.fixture
def enrolled_only(w3: Web3) -> ChecksumAddress:
    """Admitted by the admin but not registered."""
    return w3.eth.accounts[4]


@pytest.fixture
def newcomer(w3: Web3) -> ChecksumAddress:
    """Not enrolled yet; free for a test to enroll and register."""
    return w3.eth.accounts[5]


@pytest.fixture
def outsider(w3: Web3) -> ChecksumAddress:
    """Neither enrolled nor registered."""
    return w3.eth.accounts[9]


@pytest.fixture
def send(w3: Web3) -> Callable[..., TxReceipt]:
    def _send(call: ContractFunction, sender: str, gas: int | None = None) -> TxReceipt:
        return send_transaction(w3, call, sender, gas)

    return _send


@pytest.fixture
def emitted(authros: Contract) -> Callable[[TxReceipt, str], list[dict[str, Any]]]:
    """The arguments of every log in the receipt, asserting all are `event_name` from AuthROS."""

    def _emitted(receipt: TxReceipt, event_name: str) -> list[dict[str, Any]]:
        events = authros.events[event_name]().process_receipt(receipt, errors=STRICT)
        assert len(events) == len(receipt["logs"])
        assert all(event["address"] == authros.address for event in events)
        return [dict(event["args"]) for event in events]

    return _emitted


@pytest.fixture
def reverts(artifact: dict[str, Any]) -> RevertExpectation:
    """`with reverts("NotAdmin", caller): ...` asserts the exact custom error and arguments."""

    @contextmanager
    def _reverts(name: str, *args: Any) -> Iterator[None]:
        with pytest.raises(ContractLogicError) as info:
            yield
        assert decode_revert(artifact["abi"], info.value) == (name, args)

    return _reverts
