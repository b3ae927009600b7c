"""What the chain client raises, and the one translation of a node's failures into it.

`ChainError` is the base of everything; the callers act on its kinds (retry later on
`ChainUnavailable`, wait for gas on `InsufficientFunds`, fail for good on most
`TransactionReverted`). `translated_errors` turns transport failures (the node, a proxy in
front of it, the nonce store) into `ChainUnavailable` around every request; `refusal_explained`
turns the node's refusal of an eth_call or an estimate into the contract's custom error,
decoded from its revert data, or a sender who cannot pay.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import requests
from hexbytes import HexBytes
from web3.exceptions import ProviderConnectionError

from chainworker.codec import PANIC_SELECTOR, ContractArtifact
from chainworker.nonces import NonceLockTimeout, NonceStoreUnavailable

INSUFFICIENT_FUNDS = re.compile(
    r"insufficient funds|cannot afford|not have enough balance", re.IGNORECASE
)
NONCE_REFUSED = re.compile(
    r"nonce too low|nonce too high|invalid (transaction )?nonce|"
    r"replacement transaction underpriced",
    re.IGNORECASE,
)
# The node has this very transaction already (an earlier send that timed out did arrive):
# it is sent, and signing it again with another nonce would send it twice.
ALREADY_KNOWN = re.compile(r"already known|known transaction|already imported", re.IGNORECASE)


class ChainError(Exception):
    """Base of everything this client raises."""


class NodeRefused(ChainError):
    """The node answered a JSON-RPC request with an error (see `chainworker.rpc.NodeRpc`):
    its message, and the revert data if it carried any."""

    def __init__(self, label: str, message: str, data: str | None = None) -> None:
        super().__init__(f"{label}: the node refused the call: {message}")
        self.message = message
        self.data = data


class ChainUnavailable(ChainError):
    """The node (or the nonce store) cannot be reached; retry later."""


class ContractNotDeployed(ChainError):
    """No AuthROS contract is known for this chain (run `manage.py chain_deploy`)."""


class TransactionReverted(ChainError):
    """The contract refused the call; `error_name` is its custom error (e.g. NotRegistered)."""

    def __init__(
        self,
        error_name: str,
        error_args: dict[str, Any] | None = None,
        *,
        tx_hash: str | None = None,
        function: str | None = None,
    ) -> None:
        self.error_name = error_name
        self.error_args = error_args or {}
        self.tx_hash = tx_hash
        self.function = function
        args = ", ".join(f"{k}={_display(v)}" for k, v in self.error_args.items())
        where = f" in {function}" if function else ""
        super().__init__(f"contract refused{where}: {error_name}({args})")


class TransactionTimeout(ChainError):
    """The transaction was sent but no receipt (or not enough confirmations) came in time."""

    def __init__(self, tx_hash: str, timeout: float) -> None:
        self.tx_hash = tx_hash
        super().__init__(f"no receipt for {tx_hash} within {timeout:.0f}s")


class TransactionDropped(ChainError):
    """The node will never mine a transaction we sent: it no longer holds it, or holds it
    behind a gap in its sender's nonces (the node lost the sender's earlier transactions: it
    restarted without them, or lost its latest blocks). Send again; the sender's nonce counter
    was resynced from the node when the gap was seen."""

    def __init__(self, tx_hash: str, reason: str) -> None:
        self.tx_hash = tx_hash
        super().__init__(f"{tx_hash} will never be mined: {reason}")


class NonceError(ChainError):
    """The node kept refusing our nonce even after resyncing from it."""


class InsufficientFunds(ChainError):
    """The sender cannot pay for gas (fund the EOA from the operator)."""


def _display(value: Any) -> str:
    if isinstance(value, bytes | bytearray):
        return "0x" + bytes(value).hex()
    return str(value)


@contextmanager
def translated_errors() -> Iterator[None]:
    """Turn transport failures into ChainUnavailable, for every request to the node."""
    try:
        yield
    except (requests.ConnectionError, requests.Timeout, ProviderConnectionError) as exc:
        raise ChainUnavailable(f"chain node unreachable: {exc}") from exc
    except requests.HTTPError as exc:
        # A proxy or load balancer in front of the node answering 429 or 5xx: try later.
        raise ChainUnavailable(f"chain node answered HTTP error: {exc}") from exc
    except (NonceStoreUnavailable, NonceLockTimeout) as exc:
        raise ChainUnavailable(str(exc)) from exc


def revert_decoded(
    artifact: ContractArtifact,
    data: str | bytes | None,
    message: str | None,
    *,
    function: str | None,
    tx_hash: str | None = None,
) -> TransactionReverted:
    """The contract's custom error from a revert's data, or the node's reason when the data
    names none."""
    name, args = artifact.decode_error(data)
    if name == "Reverted" and message:
        args = {"reason": message}
    return TransactionReverted(name, args, tx_hash=tx_hash, function=function)


def refusal_explained(
    refused: NodeRefused,
    *,
    artifact: ContractArtifact,
    label: str,
    sender: str | None = None,
    tx_hash: str | None = None,
) -> ChainError:
    """What a node's refusal to call or estimate means: the contract's revert (decoded), a
    sender who cannot pay, or the node's own refusal."""
    if sender is not None and INSUFFICIENT_FUNDS.search(refused.message):
        return InsufficientFunds(f"{sender} cannot pay for {label}")
    data = HexBytes(refused.data) if refused.data else None
    if data and bytes(data[:4]) == PANIC_SELECTOR:
        return TransactionReverted(
            "Panic", {"detail": refused.message}, tx_hash=tx_hash, function=label
        )
    if data or "revert" in refused.message.lower():
        return revert_decoded(artifact, data, refused.message, function=label, tx_hash=tx_hash)
    return refused
