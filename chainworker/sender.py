"""Sending transactions: the one way the client builds, signs and submits one, and awaits it.

`TransactionSender` is what `chainworker.client.AuthROSChain` sends with: the chain's identity
(its id signs every transaction, its id and genesis name the nonce counters), the fees, and
one transaction builder for every kind of send (a contract function, a deployment, a value
transfer). A transaction is written here, not by web3's contract layer: the gas estimate (unless
given) and the fees are asked in one JSON-RPC batch, the transaction signed locally by the
sending account under its nonce lock (`chainworker.nonces`), sent raw, and its receipt polled
by single requests (`chainworker.rpc.NodeRpc`): 10.7 to 5.5 ms of CPU per anchorRoot and its
receipt against web3's build_transaction and wait_for_transaction_receipt.

A receipt wait also asks the node now and then whether it can still mine the transaction at
all (one it lost, or holds behind a nonce gap, is TransactionDropped at once), waits for the
configured confirmations, and replays a reverted transaction as an eth_call to name the
contract's error.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from functools import cached_property
from typing import Any

import redis
from eth_account.signers.local import LocalAccount
from eth_utils import ValidationError as EthValidationError
from hexbytes import HexBytes
from web3._utils.method_formatters import receipt_formatter
from web3.exceptions import TransactionNotFound, Web3RPCError
from web3.types import TxReceipt

from chainworker.codec import ContractArtifact
from chainworker.errors import (
    ALREADY_KNOWN,
    INSUFFICIENT_FUNDS,
    NONCE_REFUSED,
    InsufficientFunds,
    NodeRefused,
    NonceError,
    TransactionDropped,
    TransactionReverted,
    TransactionTimeout,
    refusal_explained,
    translated_errors,
)
from chainworker.nonces import RedisNonceManager
from chainworker.rpc import NodeRpc, connect
from core.metrics import chain_transaction_observed

logger = logging.getLogger(__name__)

# Gas estimates are taken against the pending state; a margin absorbs small state changes.
GAS_MARGIN = 1.2
# Gas of a plain value transfer.
TRANSFER_GAS = 21_000
# How often a receipt wait asks whether the node can still mine the transaction at all.
DROPPED_CHECK_INTERVAL = 5.0
# Contract functions of transactions sent lately kept for their receipts' metrics.
SENT_FUNCTIONS_KEPT = 4096


class TransactionSender:
    """Signs, sends and awaits transactions on the node at `url` (the base of the client)."""

    def __init__(
        self,
        url: str,
        *,
        redis_client: redis.Redis,
        artifact: ContractArtifact,
        receipt_timeout: float,
        rpc_timeout: float,
        confirmations: int,
        poll_interval: float,
        redis_prefix: str,
        nonce_lock_timeout: float,
    ) -> None:
        self.url = url
        self.w3 = connect(url, timeout=rpc_timeout)
        self.rpc = NodeRpc(self.w3)
        self.artifact = artifact
        self.receipt_timeout = receipt_timeout
        self.confirmations = confirmations
        self.poll_interval = poll_interval
        self._redis = redis_client
        self._redis_prefix = redis_prefix
        self._nonce_lock_timeout = nonce_lock_timeout
        # The contract function of each transaction sent lately, for the metrics of a receipt
        # awaited without naming it (anchoring's).
        self._sent_functions: OrderedDict[str, str] = OrderedDict()
        self._sent_lock = threading.Lock()

    # identity -------------------------------------------------------------------------

    @cached_property
    def chain_id(self) -> int:
        with translated_errors():
            return int(self.w3.eth.chain_id)

    @cached_property
    def genesis_hash(self) -> str:
        with translated_errors():
            return "0x" + bytes(self.w3.eth.get_block(0)["hash"]).hex()

    @cached_property
    def chain_key(self) -> str:
        """Identifies this chain across processes: its id and genesis."""
        return f"{self.chain_id}:{self.genesis_hash[:18]}"

    @cached_property
    def nonces(self) -> RedisNonceManager:
        return RedisNonceManager(
            self._redis,
            namespace=self.chain_key,
            prefix=self._redis_prefix,
            lock_timeout=self._nonce_lock_timeout,
        )

    def fee_per_gas(self) -> int:
        """The most a gas unit of a transaction sent now may cost (its max fee per gas, or the
        legacy gas price), as the transactions this client sends set it; 0 on a zero-gas chain."""
        with translated_errors():
            fees = self._priced({}, sender=None, label="fees")
        return int(fees.get("maxFeePerGas", fees.get("gasPrice", 0)))

    # sending --------------------------------------------------------------------------

    def send(
        self,
        sender: LocalAccount,
        *,
        label: str,
        to: str | None,
        data: bytes = b"",
        value: int = 0,
        gas: int | None = None,
        function: str | None = None,
        attempts: int = 3,
    ) -> str:
        """Sign and submit one transaction under the sender's nonce lock; return its hash.

        `to` None deploys `data`; `function` is the contract function it calls, kept for its
        receipt's metrics. Gas is estimated (unless given) before the lock is taken, so the lock
        is held only to choose the nonce, sign and hand the transaction to the node.
        """
        with translated_errors():
            tx = self._build(sender, to=to, data=data, value=value, gas=gas, label=label)
        with translated_errors(), self.nonces.reserve(sender.address, self._pending_nonce) as slot:
            for attempt in range(1, attempts + 1):
                signed = sender.sign_transaction({**tx, "nonce": slot.nonce})
                slot.hold()
                try:
                    tx_hash = "0x" + self._send_raw(signed.raw_transaction, label=label).hex()
                except (NodeRefused, Web3RPCError, EthValidationError, ValueError) as exc:
                    message = str(exc)
                    if ALREADY_KNOWN.search(message):
                        slot.commit()
                        tx_hash = "0x" + bytes(signed.hash).hex()
                        break
                    if INSUFFICIENT_FUNDS.search(message):
                        raise InsufficientFunds(f"{sender.address} cannot pay for {label}") from exc
                    if not NONCE_REFUSED.search(message):
                        raise
                    logger.warning(
                        "nonce %s refused for %s (%s); resyncing from the node",
                        slot.nonce,
                        sender.address,
                        message,
                    )
                    if attempt == attempts:
                        raise NonceError(
                            f"node kept refusing nonces for {sender.address}: {message}"
                        ) from exc
                    slot.resync()
                    continue
                slot.commit()
                break
        if function is not None:
            with self._sent_lock:
                self._sent_functions[tx_hash] = function
                while len(self._sent_functions) > SENT_FUNCTIONS_KEPT:
                    self._sent_functions.popitem(last=False)
        return tx_hash

    def _build(
        self,
        sender: LocalAccount,
        *,
        to: str | None,
        data: bytes,
        value: int,
        gas: int | None,
        label: str,
    ) -> dict[str, Any]:
        """The transaction without its nonce: gas estimated (unless given) and fees asked in
        one JSON-RPC batch, the transaction written here."""
        tx: dict[str, Any] = {
            "from": sender.address,
            "chainId": self.chain_id,
            "data": "0x" + data.hex(),
            "value": value,
        }
        if to is not None:
            tx["to"] = to
        estimate = None
        if gas is None:
            # At zero fees: the gas does not depend on them, and a sender funded for the gas it
            # needs cannot cover a node's estimate at the block gas limit.
            estimate = {key: tx[key] for key in ("from", "to", "data") if key in tx}
            estimate["gasPrice"] = "0x0"
            if value:
                estimate["value"] = hex(value)
        try:
            return self._priced(tx, sender=sender.address, label=label, estimate=estimate, gas=gas)
        except (Web3RPCError, EthValidationError, ValueError) as exc:
            if INSUFFICIENT_FUNDS.search(str(exc)):
                raise InsufficientFunds(f"{sender.address} cannot pay for {label}") from exc
            raise

    def _priced(
        self,
        tx: dict[str, Any],
        *,
        sender: str | None,
        label: str,
        estimate: dict[str, Any] | None = None,
        gas: int | None = None,
    ) -> dict[str, Any]:
        """`tx` with its fees, and its gas (`gas`, or the node's estimate of `estimate` with a
        margin): the latest block, gas price, tip and estimate asked in one batch."""
        asked = [
            ("eth_getBlockByNumber", ["latest", False]),
            ("eth_gasPrice", []),
            ("eth_maxPriorityFeePerGas", []),
        ]
        if estimate is not None:
            asked.append(("eth_estimateGas", [estimate]))
        block, gas_price, tip, *estimated = self.rpc.batch(asked, label=label)
        for answer in (*estimated, block, gas_price):  # a refused estimate says why first
            if isinstance(answer, NodeRefused):
                raise refusal_explained(answer, artifact=self.artifact, label=label, sender=sender)
        if estimated:
            gas = int(int(estimated[0], 16) * GAS_MARGIN)
        if gas is not None:
            tx["gas"] = gas
        base_fee = block.get("baseFeePerGas") if isinstance(block, dict) else None
        return self._fees(
            tx,
            base_fee=None if base_fee is None else int(base_fee, 16),
            gas_price=lambda: int(gas_price, 16),
            # A node without eth_maxPriorityFeePerGas: web3's estimate from the fee history.
            tip=lambda: (
                int(self.w3.eth.max_priority_fee) if isinstance(tip, NodeRefused) else int(tip, 16)
            ),
        )

    @staticmethod
    def _fees(
        params: dict[str, Any],
        *,
        base_fee: int | None,
        gas_price: Callable[[], int],
        tip: Callable[[], int],
    ) -> dict[str, Any]:
        """params with their fees: the legacy gas price on a chain without a base fee, else
        twice the base fee plus the node's tip (none on a zero-gas chain)."""
        if base_fee is None:
            params["gasPrice"] = gas_price()
            return params
        # A zero-gas chain (a private PoA network): no fee, so unfunded EOAs can send too.
        free = base_fee == 0 and gas_price() == 0
        priority = 0 if free else tip()
        params["maxPriorityFeePerGas"] = priority
        params["maxFeePerGas"] = 2 * base_fee + priority
        return params

    def _send_raw(self, raw: bytes, *, label: str) -> bytes:
        answer = self.rpc.request("eth_sendRawTransaction", ["0x" + raw.hex()], label=label)
        return bytes(HexBytes(answer))

    def _pending_nonce(self, address: str) -> int:
        count = self.rpc.request("eth_getTransactionCount", [address, "pending"], label="nonce")
        return int(count, 16)

    def resync_nonce(self, address: str) -> None:
        """Forget our nonce counter for `address` (after a timeout or a dropped transaction)."""
        with translated_errors():
            self.nonces.forget(address)

    # receipts -------------------------------------------------------------------------

    def wait_for_receipt(
        self, tx_hash: str, *, timeout: float | None = None, function: str | None = None
    ) -> TxReceipt:
        """Wait for the receipt and the configured confirmations; raise if it reverted."""
        timeout = self.receipt_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        with translated_errors():
            receipt = self._receipt_poll(tx_hash, deadline, timeout)
            with self._sent_lock:
                sent_function = self._sent_functions.pop(tx_hash, None)
            chain_transaction_observed(
                function or sent_function,
                ok=receipt["status"] == 1,
                gas_used=int(receipt["gasUsed"]),
            )
            if receipt["status"] != 1:
                raise self._explain_failure(receipt, tx_hash, function)
            self._await_confirmations(receipt, tx_hash, deadline, timeout)
        return receipt

    def _receipt_poll(self, tx_hash: str, deadline: float, timeout: float) -> TxReceipt:
        """The receipt, asked every poll_interval by single requests (a receipt is formatted
        as web3 formats it once it is there). A node that cannot tell yet (geth while it
        indexes transactions) is asked again, as web3 does.

        Every DROPPED_CHECK_INTERVAL, and when the time is up, the node is asked whether it can
        still mine the transaction at all: one it lost, or holds behind a nonce gap, raises
        TransactionDropped at once instead of being waited for until the timeout."""
        checked = time.monotonic()
        while True:
            try:
                raw = self.rpc.request("eth_getTransactionReceipt", [tx_hash], label="receipt")
            except NodeRefused as refused:
                logger.debug("receipt of %s not known yet: %s", tx_hash, refused.message)
                raw = None
            if isinstance(raw, dict) and raw.get("blockHash") is not None:
                return receipt_formatter(raw)
            now = time.monotonic()
            if now >= deadline or now - checked >= DROPPED_CHECK_INTERVAL:
                checked = now
                if never := self._transaction_fate(tx_hash)[1]:
                    raise TransactionDropped(tx_hash, never)
            if now >= deadline:
                raise TransactionTimeout(tx_hash, timeout)
            time.sleep(min(self.poll_interval, max(deadline - time.monotonic(), 0)))

    def _await_confirmations(
        self, receipt: TxReceipt, tx_hash: str, deadline: float, timeout: float
    ) -> None:
        target = int(receipt["blockNumber"]) + self.confirmations
        while self.confirmations and int(self.w3.eth.block_number) < target:
            if time.monotonic() > deadline:
                raise TransactionTimeout(tx_hash, timeout)
            time.sleep(self.poll_interval)
        if self.confirmations:
            # A reorganisation may have dropped the transaction while we waited.
            try:
                again = self.w3.eth.get_transaction_receipt(HexBytes(tx_hash))
            except TransactionNotFound as exc:
                raise TransactionTimeout(tx_hash, timeout) from exc
            if again["blockHash"] != receipt["blockHash"]:
                raise TransactionTimeout(tx_hash, timeout)

    def _explain_failure(
        self, receipt: TxReceipt, tx_hash: str, function: str | None
    ) -> TransactionReverted:
        """Replay a failed transaction as an eth_call at its parent block to recover its
        custom error."""
        label = function or "replay"
        tx = self.rpc.request("eth_getTransactionByHash", [tx_hash], label=label)
        call = {key: tx[key] for key in ("from", "to", "value") if tx.get(key) is not None}
        call["data"] = tx["input"]
        try:
            self.rpc.call(call, label=label, block=int(receipt["blockNumber"]) - 1)
        except NodeRefused as refused:
            explained = refusal_explained(
                refused, artifact=self.artifact, label=label, tx_hash=tx_hash
            )
            if isinstance(explained, TransactionReverted):
                return TransactionReverted(
                    explained.error_name, explained.error_args, tx_hash=tx_hash, function=function
                )
        return TransactionReverted("Reverted", {}, tx_hash=tx_hash, function=function)

    # a transaction's fate -------------------------------------------------------------

    def transaction_pending(self, tx_hash: str) -> bool:
        """Whether the node holds the transaction ready to mine and has not mined it yet. One
        it holds behind a gap in its sender's nonces is not: it waits for transactions the
        node lost, and is mined only if someone sends them (the sender's nonce counter is
        resynced then, see _transaction_fate)."""
        mined, never = self._transaction_fate(tx_hash)
        return not mined and not never

    def _transaction_fate(self, tx_hash: str) -> tuple[bool, str]:
        """(mined, why the node will never mine it): "" while it may. Never: the node does not
        hold it, or holds it behind a nonce gap. A gap means the node lost its sender's earlier
        transactions, so the sender's nonce counter is resynced: the next send counts from the
        node instead of queueing behind the gap too."""
        with translated_errors():
            try:
                tx = self.w3.eth.get_transaction(HexBytes(tx_hash))
            except TransactionNotFound:
                return False, "the node does not hold it"
            if tx.get("blockNumber") is not None:
                return True, ""
            ready = self._pending_nonce(tx["from"])
        if tx["nonce"] < ready:
            return False, ""
        self.resync_nonce(tx["from"])
        return False, (
            f"its nonce {tx['nonce']} waits behind a gap (the node's next nonce for "
            f"{tx['from']} is {ready}: it lost the transactions before it)"
        )
