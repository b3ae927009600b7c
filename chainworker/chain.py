"""The one web3 client for the AuthROS contract.

`AuthROSChain` connects to a node by its JSON-RPC URL (``http(s)://``: geth, anvil, a PoA
network; the tests run one anvil per session), deploys or loads the contract, and wraps each
contract function as a typed method. Transactions are signed locally by the sending account;
nonces come from `RedisNonceManager`, so any number of processes may send. This module does not
import Django: `chainworker.services.chain_client()` builds the client from settings.
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
import time
import uuid
import weakref
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path
from typing import Any

import redis
import requests
from eth_abi import decode as abi_decode
from eth_abi import encode as abi_encode
from eth_account.signers.local import LocalAccount
from eth_utils import ValidationError as EthValidationError
from eth_utils import event_abi_to_log_topic, function_abi_to_4byte_selector, keccak
from hexbytes import HexBytes
from web3 import Web3
from web3._utils.method_formatters import receipt_formatter
from web3.exceptions import (
    BadFunctionCallOutput,
    ContractLogicError,
    ContractPanicError,
    ProviderConnectionError,
    TransactionNotFound,
    Web3RPCError,
)
from web3.middleware import ExtraDataToPOAMiddleware
from web3.types import TxReceipt

from chainworker.nonces import NonceLockTimeout, NonceStoreUnavailable, RedisNonceManager
from core.metrics import chain_transaction_observed
from smcrypto.sm3 import sm3_digest

logger = logging.getLogger(__name__)

ARTIFACT_PATH = Path(__file__).resolve().parent.parent / "contracts" / "build" / "AuthROS.json"
ZERO_ADDRESS = "0x" + "00" * 20
ZERO_BYTES32 = b"\x00" * 32
# Gas estimates are taken against the pending state; a margin absorbs small state changes.
GAS_MARGIN = 1.2
# Gas for anchorRoot sent without an estimate (a root following one in flight): a sender's
# first root takes about 70,000, the next ones about 55,000, whatever the tree's size.
ANCHOR_ROOT_GAS = 120_000
# A robot's SM2 public key as robotKeyAdd takes it: x||y, without the 04 marker.
ROBOT_PUBLIC_KEY_LENGTH = 64
_INSUFFICIENT_FUNDS = re.compile(
    r"insufficient funds|cannot afford|not have enough balance", re.IGNORECASE
)
_NONCE_ERROR = re.compile(
    r"nonce too low|nonce too high|invalid (transaction )?nonce|"
    r"replacement transaction underpriced",
    re.IGNORECASE,
)
# The node has this very transaction already (an earlier send that timed out did arrive):
# it is sent, and signing it again with another nonce would send it twice.
_ALREADY_KNOWN = re.compile(r"already known|known transaction|already imported", re.IGNORECASE)
# How often a receipt wait asks whether the node can still mine the transaction at all.
DROPPED_CHECK_INTERVAL = 5.0


# --- errors ------------------------------------------------------------------------------


class ChainError(Exception):
    """Base of everything this client raises."""


class NodeRefused(ChainError):
    """The node answered a JSON-RPC request with an error (a lean request's; see
    `AuthROSChain._rpc_lean`): its message, and the revert data if it carried any."""

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


# --- value conversions ---------------------------------------------------------------------


def record_id_to_bytes32(record_id: uuid.UUID | str) -> bytes:
    """A record id on chain: the 16 UUID bytes, left-aligned, zero-padded to 32."""
    value = record_id if isinstance(record_id, uuid.UUID) else uuid.UUID(str(record_id))
    return value.bytes + b"\x00" * 16


def bytes32_to_record_id(value: bytes) -> uuid.UUID:
    return uuid.UUID(bytes=bytes(value[:16]))


def data_type_to_bytes32(data_type: str) -> bytes:
    """A ROS type on chain: UTF-8 left-aligned if it fits in 32 bytes, else its keccak hash."""
    raw = data_type.encode("utf-8")
    if not raw or b"\x00" in raw:
        raise ValueError("data type must be a non-empty string without NUL characters")
    if len(raw) <= 32:
        return raw.ljust(32, b"\x00")
    return keccak(raw)


def bytes32_to_data_type(value: bytes) -> str:
    """Inverse of `data_type_to_bytes32` where possible; a hashed type is shown as hex."""
    stripped = bytes(value).rstrip(b"\x00")
    try:
        text = stripped.decode("utf-8")
    except UnicodeDecodeError:
        return "0x" + bytes(value).hex()
    return text if text.isprintable() and b"\x00" not in stripped else "0x" + bytes(value).hex()


def datetime_to_chain_time(moment: datetime) -> int:
    """Times on chain are microseconds since the Unix epoch (UTC)."""
    if moment.tzinfo is None:
        raise ValueError("capture time must be timezone-aware")
    delta = moment - datetime(1970, 1, 1, tzinfo=UTC)
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds


def chain_time_to_datetime(value: int) -> datetime:
    seconds, micros = divmod(int(value), 1_000_000)
    return datetime.fromtimestamp(seconds, tz=UTC).replace(microsecond=micros)


# --- results -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChainEvent:
    name: str
    args: dict[str, Any]
    block_number: int
    tx_hash: str
    log_index: int


@dataclass(frozen=True)
class TxResult:
    tx_hash: str
    block_number: int
    gas_used: int
    events: list[ChainEvent] = field(default_factory=list)


@dataclass(frozen=True)
class OnChainRecord:
    record_id: uuid.UUID
    owner: str
    digest: bytes
    time: datetime
    data_type: str


@dataclass(frozen=True)
class OnChainRoot:
    """A Merkle root as its sender anchored it (rootOf)."""

    sender: str
    root: bytes
    size: int
    time: datetime
    block_number: int


@dataclass(frozen=True)
class OnChainGrant:
    """A grant as the contract holds it (grantOf): `live` is granted and not expired at the
    latest block; `scope` is its scope commitment (zeros: all records), `expiry` unix seconds
    (0: never)."""

    live: bool
    scope: bytes
    expiry: int


@dataclass(frozen=True)
class RobotKeyOnChain:
    """A robot's signing key as the contract holds it (robotKeyOf): the EOA that added it
    (None: never added), the block it was added in and the block it was revoked in (None:
    live)."""

    owner: str | None
    added_block: int
    revoked_block: int | None

    def live_at(self, block: int) -> bool:
        """Whether the key counts for what was anchored in `block`: added at or before it and
        not revoked by then (DESIGN.md "A record is genuine")."""
        return (
            self.owner is not None
            and self.added_block <= block
            and (self.revoked_block is None or block < self.revoked_block)
        )


@dataclass(frozen=True)
class AnchorItem:
    """One record to anchor: what `dataUpload` and `dataUploadBatch` take per record."""

    record_id: uuid.UUID
    digest: bytes
    time: datetime
    data_type: str

    def as_args(self) -> tuple[bytes, bytes, int, bytes]:
        if len(self.digest) != 32:
            raise ValueError("digest must be 32 bytes (SM3)")
        return (
            record_id_to_bytes32(self.record_id),
            bytes(self.digest),
            datetime_to_chain_time(self.time),
            data_type_to_bytes32(self.data_type),
        )


@dataclass(frozen=True)
class ContractArtifact:
    abi: list[dict[str, Any]]
    bytecode: str
    compiler_version: str
    source_keccak: str

    @classmethod
    def load(cls, path: Path = ARTIFACT_PATH) -> ContractArtifact:
        data = json.loads(Path(path).read_text())
        return cls(
            abi=data["abi"],
            bytecode=data["bytecode"],
            compiler_version=data["compiler"]["version"],
            source_keccak=data["source"]["keccak256"],
        )

    @cached_property
    def errors_by_selector(self) -> dict[bytes, dict[str, Any]]:
        return {
            function_abi_to_4byte_selector(entry): entry
            for entry in self.abi
            if entry.get("type") == "error"
        }

    def decode_error(self, data: str | bytes | None) -> tuple[str, dict[str, Any]]:
        """Name and arguments of a revert, from its raw return data."""
        raw = HexBytes(data) if data else HexBytes(b"")
        entry = self.errors_by_selector.get(bytes(raw[:4]))
        if entry is None:
            return ("UnknownRevert", {"data": bytes(raw)}) if raw else ("Reverted", {})
        types = [arg["type"] for arg in entry["inputs"]]
        values = abi_decode(types, bytes(raw[4:])) if types else ()
        args = {
            arg["name"]: Web3.to_checksum_address(v) if arg["type"] == "address" else v
            for arg, v in zip(entry["inputs"], values, strict=True)
        }
        return entry["name"], args


@dataclass(frozen=True)
class _Calldata:
    """A contract call encoded here (a real node's transactions): where and what."""

    to: str
    data: bytes


# Revert data of a Solidity panic (assert, overflow): Panic(uint256).
_PANIC_SELECTOR = bytes.fromhex("4e487b71")


# --- connections ---------------------------------------------------------------------------


def connect(url: str, *, timeout: float = 10.0) -> Web3:
    """A Web3 connection for the node at `url`."""
    if url.startswith(("http://", "https://")):
        # web3 asks the node for its chain id before every eth_call and transaction; a node's
        # chain id does not change, so it is asked once per connection (a view is one eth_call).
        provider = Web3.HTTPProvider(
            url,
            request_kwargs={"timeout": timeout},
            session=rpc_session(url),
            cache_allowed_requests=True,
            cacheable_requests={"eth_chainId"},
        )
        w3 = Web3(provider)
        # Proof-of-authority networks (geth clique) carry signer data in extraData.
        w3.middleware_onion.inject(ExtraDataToPOAMiddleware, layer=0)
        return w3
    raise ValueError(f"unsupported chain URL {url!r}: use http(s)://host:port")


SENT_FUNCTIONS_KEPT = 4096
# Connections kept to the node per process: a web process's threads and a worker's share them.
RPC_POOL_SIZE = 32


def rpc_session(url: str) -> requests.Session:
    """The HTTP session of every call to the node at `url`, shared by this process's threads.

    Proxies and the CA bundle come from the environment, read here once: requests otherwise
    reads every variable of the environment again at each call (HTTP(S)_PROXY, NO_PROXY,
    REQUESTS_CA_BUNDLE), about a tenth of a chain worker's CPU. A forked child closes its
    copy's connections (it opens its own).
    """
    session = requests.Session()
    session.trust_env = False
    proxies = requests.utils.get_environ_proxies(url)
    session.proxies.update({scheme: at for scheme, at in proxies.items() if scheme != "no"})
    bundle = os.environ.get("REQUESTS_CA_BUNDLE") or os.environ.get("CURL_CA_BUNDLE")
    if bundle:
        session.verify = bundle
    adapter = requests.adapters.HTTPAdapter(pool_connections=1, pool_maxsize=RPC_POOL_SIZE)
    session.mount("http://", adapter)
    session.mount("https://", adapter)
    # A process forked from this one (Celery's pool, from a parent that checked the chain)
    # must not share its open connections: two processes reading answers from one socket get
    # each other's. The child drops them and opens its own.
    held = weakref.ref(session)
    os.register_at_fork(after_in_child=lambda: _session_forget_connections(held))
    return session


def _session_forget_connections(held: weakref.ref[requests.Session]) -> None:
    session = held()
    if session is not None:
        session.close()


@contextmanager
def _translated_errors(function: str | None = None) -> Iterator[None]:
    """Turn transport failures into ChainUnavailable, for every call into web3."""
    try:
        yield
    except (requests.ConnectionError, requests.Timeout, ProviderConnectionError) as exc:
        raise ChainUnavailable(f"chain node unreachable: {exc}") from exc
    except requests.HTTPError as exc:
        # A proxy or load balancer in front of the node answering 429 or 5xx: try later.
        raise ChainUnavailable(f"chain node answered HTTP error: {exc}") from exc
    except (NonceStoreUnavailable, NonceLockTimeout) as exc:
        raise ChainUnavailable(str(exc)) from exc


# --- the client ----------------------------------------------------------------------------


class AuthROSChain:
    """Typed access to one AuthROS contract on one chain."""

    def __init__(
        self,
        url: str,
        *,
        redis_client: redis.Redis,
        contract_address: str | None = None,
        artifact: ContractArtifact | None = None,
        receipt_timeout: float = 120.0,
        rpc_timeout: float = 10.0,
        confirmations: int = 0,
        poll_interval: float = 0.1,
        redis_prefix: str = "authros",
        nonce_lock_timeout: float = 15.0,
    ) -> None:
        self.url = url
        self.w3 = connect(url, timeout=rpc_timeout)
        self.artifact = artifact or ContractArtifact.load()
        self.receipt_timeout = receipt_timeout
        self.confirmations = confirmations
        self.poll_interval = poll_interval
        self._redis = redis_client
        self._redis_prefix = redis_prefix
        self._nonce_lock_timeout = nonce_lock_timeout
        self._address: str | None = None
        self._contract: Any = None
        self._scoped_grants: dict[str, bool] = {}  # contract address -> has grantOf
        # The contract function of each transaction this client sent lately, for the metrics
        # of a receipt awaited without naming it (anchoring's).
        self._sent_functions: OrderedDict[str, str] = OrderedDict()
        self._sent_lock = threading.Lock()
        if contract_address:
            self.use_contract(contract_address)

    # identity -------------------------------------------------------------------------

    @cached_property
    def chain_id(self) -> int:
        with _translated_errors():
            return int(self.w3.eth.chain_id)

    @cached_property
    def genesis_hash(self) -> str:
        with _translated_errors():
            return "0x" + bytes(self.w3.eth.get_block(0)["hash"]).hex()

    @cached_property
    def client_version(self) -> str:
        with _translated_errors():
            return str(self.w3.client_version)

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

    def latest_block(self) -> int:
        with _translated_errors():
            return int(self.w3.eth.block_number)

    def balance(self, address: str) -> int:
        with _translated_errors():
            return int(self.w3.eth.get_balance(Web3.to_checksum_address(address)))

    def fee_per_gas(self) -> int:
        """The most a gas unit of a transaction sent now may cost (its max fee per gas, or the
        legacy gas price), as the transactions this client sends set it; 0 on a zero-gas chain."""
        with _translated_errors():
            fees = self._fill_fees({})
        return int(fees.get("maxFeePerGas", fees.get("gasPrice", 0)))

    def is_connected(self) -> bool:
        try:
            self.latest_block()
        except ChainUnavailable:
            return False
        return True

    def head(self) -> tuple[int, int]:
        """The latest block's number and timestamp (seconds since the epoch)."""
        with _translated_errors():
            block = self.w3.eth.get_block("latest")
        return int(block["number"]), int(block["timestamp"])

    def pending_transaction_count(self) -> int | None:
        """Transactions the node holds ready to mine and has not mined: txpool_status's
        "pending" (anvil, geth, Nethermind), else the pending block's; None if it tells neither."""
        with _translated_errors():
            status = self.w3.provider.make_request("txpool_status", []).get("result")
            if isinstance(status, dict) and "pending" in status:
                return int(str(status["pending"]), 0)
            pending = self.w3.provider.make_request("eth_getBlockByNumber", ["pending", False])
        block = pending.get("result")
        return len(block.get("transactions") or []) if isinstance(block, dict) else None

    # contract -------------------------------------------------------------------------

    @property
    def address(self) -> str:
        if self._address is None:
            raise ContractNotDeployed("no AuthROS contract address is set for this chain")
        return self._address

    @property
    def contract(self) -> Any:
        if self._contract is None:
            raise ContractNotDeployed("no AuthROS contract address is set for this chain")
        return self._contract

    def use_contract(self, address: str) -> None:
        self._address = Web3.to_checksum_address(address)
        self._contract = self.w3.eth.contract(address=self._address, abi=self.artifact.abi)

    def has_code(self, address: str) -> bool:
        with _translated_errors():
            return len(self.w3.eth.get_code(Web3.to_checksum_address(address))) > 0

    def deploy(self, deployer: LocalAccount) -> TxResult:
        """Deploy a new AuthROS contract (admin = deployer) and start using it."""
        factory = self.w3.eth.contract(abi=self.artifact.abi, bytecode=self.artifact.bytecode)
        tx_hash = self._send(deployer, factory.constructor(), label="deploy")
        receipt = self.wait_for_receipt(tx_hash)
        self.use_contract(receipt["contractAddress"])
        return self._result(receipt)

    def admin(self) -> str:
        return self._call("admin")

    # writes ---------------------------------------------------------------------------

    def enroll(self, admin: LocalAccount, eoa: str, *, wait: bool = True) -> TxResult | str:
        return self._transact(admin, "enroll", Web3.to_checksum_address(eoa), wait=wait)

    def register(
        self, owner: LocalAccount, commitment: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "register", _bytes32(commitment), wait=wait)

    def rotate_key(
        self, owner: LocalAccount, commitment: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "rotateKey", _bytes32(commitment), wait=wait)

    def data_upload(
        self, owner: LocalAccount, item: AnchorItem, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "dataUpload", *item.as_args(), wait=wait)

    def data_upload_batch(
        self, owner: LocalAccount, items: Sequence[AnchorItem], *, wait: bool = True
    ) -> TxResult | str:
        if not items:
            raise ValueError("a batch needs at least one record")
        columns = list(zip(*(item.as_args() for item in items), strict=True))
        return self._transact(owner, "dataUploadBatch", *map(list, columns), wait=wait)

    def anchor_root(
        self,
        sender: LocalAccount,
        root: bytes,
        size: int,
        prev_root: bytes = bytes(32),
        *,
        wait: bool = True,
        estimate: bool = True,
    ) -> TxResult | str:
        """Anchor the root of a tree of `size` records; `prev_root` is the sender's last root
        (zeros for its first): anything else is refused with WrongPrevRoot.

        estimate=False sends with ANCHOR_ROOT_GAS instead of estimating against the latest
        block: for a root that follows one still in flight, which the latest block would
        refuse (its prevRoot is not on chain yet)."""
        if size < 1:
            raise ValueError("a tree has at least one leaf")
        args = (_bytes32(root), size, _bytes32(prev_root))
        return self._transact(
            sender, "anchorRoot", *args, wait=wait, gas=None if estimate else ANCHOR_ROOT_GAS
        )

    def authority_grant(
        self, owner: LocalAccount, grantee: str, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "authorityGrant", Web3.to_checksum_address(grantee), wait=wait)

    def authority_grant_scoped(
        self, owner: LocalAccount, grantee: str, scope: bytes, expiry: int, *, wait: bool = True
    ) -> TxResult | str:
        """Grant, or change the terms of a grant: `scope` the scope commitment (zeros: all
        records), `expiry` unix seconds (0: never)."""
        return self._transact(
            owner,
            "authorityGrantScoped",
            Web3.to_checksum_address(grantee),
            _bytes32(scope),
            int(expiry),
            wait=wait,
        )

    def authority_revoke(
        self, owner: LocalAccount, grantee: str, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(
            owner, "authorityRevoke", Web3.to_checksum_address(grantee), wait=wait
        )

    def robot_key_add(
        self, sender: LocalAccount, key_hash: bytes, public_key: bytes, *, wait: bool = True
    ) -> TxResult | str:
        """Register a robot's SM2 public key `x||y` (64 bytes) under `key_hash`, its SM3.
        The contract cannot afford SM3 and would keep a wrong hash forever (a hash is added
        once), so the pair is checked here: ValueError when it does not match."""
        if len(public_key) != ROBOT_PUBLIC_KEY_LENGTH:
            raise ValueError("a robot public key is x||y: 64 bytes, without the 04 marker")
        if sm3_digest(bytes(public_key)) != _bytes32(key_hash):
            raise ValueError("key_hash is not SM3 of public_key")
        return self._transact(sender, "robotKeyAdd", bytes(key_hash), bytes(public_key), wait=wait)

    def robot_key_revoke(
        self, sender: LocalAccount, key_hash: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(sender, "robotKeyRevoke", _bytes32(key_hash), wait=wait)

    def transfer(
        self, sender: LocalAccount, to: str, value_wei: int, *, wait: bool = True
    ) -> TxResult | str:
        """Plain value transfer, e.g. the operator funding a new custodial EOA."""
        tx_hash = self._send(
            sender, None, to=Web3.to_checksum_address(to), value=value_wei, label="transfer"
        )
        return self._result(self.wait_for_receipt(tx_hash)) if wait else tx_hash

    # reads ----------------------------------------------------------------------------

    def data_query(self, record_id: uuid.UUID | str) -> OnChainRecord | None:
        """The anchored record, or None if nothing is anchored under this id yet."""
        owner, digest, when, data_type = self._call("dataQuery", record_id_to_bytes32(record_id))
        if int(owner, 16) == 0:
            return None
        return OnChainRecord(
            record_id=uuid.UUID(str(record_id)),
            owner=owner,
            digest=bytes(digest),
            time=chain_time_to_datetime(when),
            data_type=bytes32_to_data_type(data_type),
        )

    def root_of(self, sender: str, root: bytes) -> OnChainRoot | None:
        """The root as `sender` anchored it, or None if it never did (on this chain)."""
        size, when, block = self._call_lean(
            "rootOf", Web3.to_checksum_address(sender), _bytes32(root)
        )
        if int(size) == 0:
            return None
        return OnChainRoot(
            sender=Web3.to_checksum_address(sender),
            root=bytes(root),
            size=int(size),
            time=chain_time_to_datetime(when),
            block_number=int(block),
        )

    def robot_key_of(self, key_hash: bytes) -> RobotKeyOnChain:
        """A robot key by its hash (the check of every signed record: lean); owner None when
        no EOA ever added it."""
        owner, added, revoked = self._call_lean("robotKeyOf", _bytes32(key_hash))
        return RobotKeyOnChain(
            owner=None if int(owner, 16) == 0 else Web3.to_checksum_address(owner),
            added_block=int(added),
            revoked_block=int(revoked) or None,
        )

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
        with _translated_errors():
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

    def last_root_of(self, sender: str) -> bytes:
        """The last root `sender` anchored (zeros before its first)."""
        return bytes(self._call_lean("lastRootOf", Web3.to_checksum_address(sender))[0])

    def data_check(self, record_id: uuid.UUID | str, digest: bytes) -> bool:
        return bool(self._call("dataCheck", record_id_to_bytes32(record_id), _bytes32(digest)))

    def has_access(self, owner: str, viewer: str) -> bool:
        return bool(
            self._call(
                "hasAccess", Web3.to_checksum_address(owner), Web3.to_checksum_address(viewer)
            )
        )

    def grant_of(self, owner: str, grantee: str) -> OnChainGrant | None:
        """The grant from `owner` to `grantee` in one eth_call (the check at view); None when
        the contract in use predates scoped grants (no grantOf: see has_scoped_grants)."""
        if not self.has_scoped_grants():
            return None
        live, scope, expiry = self._call_lean(
            "grantOf", Web3.to_checksum_address(owner), Web3.to_checksum_address(grantee)
        )
        return OnChainGrant(live=bool(live), scope=bytes(scope), expiry=int(expiry))

    def has_scoped_grants(self) -> bool:
        """Whether the contract in use has grantOf and authorityGrantScoped: a deployment made
        before them has not (docs/grants.md says how to upgrade). Asked once per address."""
        address = self.address
        if address not in self._scoped_grants:
            try:
                self._call_lean("grantOf", ZERO_ADDRESS, ZERO_ADDRESS)
            except (ChainUnavailable, ContractNotDeployed):
                raise
            except ChainError:  # the old code reverts: no such function
                self._scoped_grants[address] = False
            else:
                self._scoped_grants[address] = True
        return self._scoped_grants[address]

    def is_enrolled(self, eoa: str) -> bool:
        return bool(self._call("isEnrolled", Web3.to_checksum_address(eoa)))

    def is_registered(self, eoa: str) -> bool:
        return bool(self._call("isRegistered", Web3.to_checksum_address(eoa)))

    def commitment_of(self, eoa: str) -> bytes:
        """The owner's key commitment (the identity check of uploads and views: lean)."""
        (commitment,) = self._call_lean("commitmentOf", Web3.to_checksum_address(eoa))
        return bytes(commitment)

    def record_count(self) -> int:
        return int(self._call("recordCount"))

    # events ---------------------------------------------------------------------------

    def events(
        self,
        from_block: int = 0,
        to_block: int | str = "latest",
        *,
        names: Sequence[str] | None = None,
    ) -> list[ChainEvent]:
        """Decoded contract events in a block range, oldest first."""
        with _translated_errors():
            logs = self.w3.eth.get_logs(
                {"address": self.address, "fromBlock": from_block, "toBlock": to_block}
            )
        decoded = [event for log in logs if (event := self._decode_log(log)) is not None]
        return [e for e in decoded if names is None or e.name in names]

    def events_naming(
        self,
        address: str,
        arguments: dict[str, Sequence[str]],
        from_block: int = 0,
        to_block: int | str = "latest",
    ) -> list[ChainEvent]:
        """Events whose indexed `arguments` (event name -> argument names) hold `address`,
        oldest first. The node filters by topic: one query per topic position, not a scan
        of every log of the contract."""
        word = "0x" + address.lower().removeprefix("0x").rjust(64, "0")
        by_position: dict[int, list[str]] = {}
        for name, names in arguments.items():
            indexed = self._indexed_arguments[name]
            for argument in names:
                if argument not in indexed:
                    raise ValueError(f"{name}.{argument} is not an indexed argument")
                topic = "0x" + self._topic_by_event[name].hex()
                by_position.setdefault(indexed.index(argument) + 1, []).append(topic)
        logs: dict[tuple[int, int], Any] = {}
        with _translated_errors():
            for position, signatures in sorted(by_position.items()):
                topics: list[Any] = [signatures, *[None] * (position - 1), word]
                for log in self.w3.eth.get_logs(
                    {
                        "address": self.address,
                        "fromBlock": from_block,
                        "toBlock": to_block,
                        "topics": topics,
                    }
                ):
                    logs[(int(log["blockNumber"]), int(log["logIndex"]))] = log
        return [
            event for _, log in sorted(logs.items()) if (event := self._decode_log(log)) is not None
        ]

    def upload_event(self, record_id: uuid.UUID | str) -> ChainEvent | None:
        """The DataUploaded event of a record (its transaction and block), if anchored."""
        topic = "0x" + bytes(self._topic_by_event["DataUploaded"]).hex()
        with _translated_errors():
            logs = self.w3.eth.get_logs(
                {
                    "address": self.address,
                    "fromBlock": 0,
                    "toBlock": "latest",
                    "topics": [topic, "0x" + record_id_to_bytes32(record_id).hex()],
                }
            )
        events = [event for log in logs if (event := self._decode_log(log)) is not None]
        return events[0] if events else None

    def root_event(self, sender: str, root: bytes) -> ChainEvent | None:
        """The RootAnchored event of a sender's root (its transaction and block), if the node
        still holds it."""
        topic = "0x" + bytes(self._topic_by_event["RootAnchored"]).hex()
        word = "0x" + Web3.to_checksum_address(sender).lower().removeprefix("0x").rjust(64, "0")
        with _translated_errors():
            logs = self.w3.eth.get_logs(
                {
                    "address": self.address,
                    "fromBlock": 0,
                    "toBlock": "latest",
                    "topics": [topic, word, "0x" + _bytes32(root).hex()],
                }
            )
        events = [event for log in logs if (event := self._decode_log(log)) is not None]
        return events[0] if events else None

    def receipt_events(self, receipt: TxReceipt) -> list[ChainEvent]:
        if self._address is None:
            return []
        return [
            event
            for log in receipt["logs"]
            if log["address"].lower() == self.address.lower()
            and (event := self._decode_log(log)) is not None
        ]

    @cached_property
    def _topic_by_event(self) -> dict[str, bytes]:
        return {
            entry["name"]: bytes(event_abi_to_log_topic(entry))
            for entry in self.artifact.abi
            if entry.get("type") == "event"
        }

    @cached_property
    def _indexed_arguments(self) -> dict[str, list[str]]:
        """Each event's indexed argument names, in topic order (topic 0 is the signature)."""
        return {
            entry["name"]: [arg["name"] for arg in entry["inputs"] if arg.get("indexed")]
            for entry in self.artifact.abi
            if entry.get("type") == "event"
        }

    @cached_property
    def _events_by_topic(self) -> dict[bytes, str]:
        return {topic: name for name, topic in self._topic_by_event.items()}

    def _decode_log(self, log: Any) -> ChainEvent | None:
        if not log["topics"]:
            return None
        name = self._events_by_topic.get(bytes(log["topics"][0]))
        if name is None:
            return None
        event = getattr(self.contract.events, name)().process_log(log)
        return ChainEvent(
            name=name,
            args=dict(event["args"]),
            block_number=int(log["blockNumber"]),
            tx_hash="0x" + bytes(log["transactionHash"]).hex(),
            log_index=int(log["logIndex"]),
        )

    # dev chains -----------------------------------------------------------------------

    def dev_faucet(self, address: str, value_wei: int) -> bool:
        """Give `address` at least `value_wei` on a development chain; False on a real one."""
        address = Web3.to_checksum_address(address)
        with _translated_errors():
            if self.client_version.lower().startswith("anvil"):
                target = self.balance(address) + value_wei
                self.w3.provider.make_request("anvil_setBalance", [address, hex(target)])
                return True
        return False

    # internals ------------------------------------------------------------------------

    def _call(self, function: str, *args: Any) -> Any:
        fn = getattr(self.contract.functions, function)(*args)
        with _translated_errors(function):
            try:
                return fn.call()
            except ContractLogicError as exc:
                raise self._reverted(exc, function) from exc
            except BadFunctionCallOutput as exc:
                # An empty answer: no code at the address (a reset chain), not a crash.
                raise ContractNotDeployed(f"{function}: no contract at {self._address}") from exc

    def _call_lean(self, function: str, *args: Any) -> tuple:
        """`_call` for the reads every view and upload makes (rootOf, grantOf, commitmentOf):
        the calldata encoded here and one eth_call sent by the provider itself, past web3's
        contract and middleware layers, which cost more than the request. A view function: it
        reverts only on bad input. Always a tuple of the function's outputs."""
        selector, inputs, outputs = self._function_types[function]
        data = selector + abi_encode(inputs, args)
        call = {"to": self.address, "data": "0x" + data.hex()}
        result = HexBytes(self._rpc_lean("eth_call", [call, "latest"], label=function) or b"")
        if not result:
            # An empty answer: no code at the address (a reset chain), not a crash.
            raise ContractNotDeployed(f"{function}: no contract at {self._address}")
        return abi_decode(outputs, result)

    def _rpc_lean(self, method: str, params: list[Any], *, label: str) -> Any:
        """One JSON-RPC request sent by the provider itself, past web3's middleware and
        formatters; its raw result, or ChainError with what the node said."""
        with _translated_errors(label):
            answer = self.w3.provider.make_request(method, params)
        return _rpc_result(answer, label)

    def _rpc_lean_batch(self, calls: list[tuple[str, list[Any]]], *, label: str) -> list[Any]:
        """`_rpc_lean` for several requests in one JSON-RPC batch (one round trip): each
        answer's result, or the NodeRefused the node's error for it makes, in order."""
        with _translated_errors(label):
            answers = self.w3.provider.make_batch_request(calls)
        if not isinstance(answers, list):  # the node refused the whole batch
            raise NodeRefused(label, _error_message(answers.get("error")))
        results: list[Any] = []
        for answer in answers:
            try:
                results.append(_rpc_result(answer, label))
            except NodeRefused as refused:
                results.append(refused)
        return results

    @cached_property
    def _function_types(self) -> dict[str, tuple[bytes, list[str], list[str]]]:
        """Each contract function's selector, input types and output types, from the ABI."""
        return {
            entry["name"]: (
                function_abi_to_4byte_selector(entry),
                [item["type"] for item in entry["inputs"]],
                [item["type"] for item in entry["outputs"]],
            )
            for entry in self.artifact.abi
            if entry.get("type") == "function"
        }

    def _transact(
        self, sender: LocalAccount, function: str, *args: Any, wait: bool, gas: int | None = None
    ) -> TxResult | str:
        # Encoded here and sent past web3's contract and middleware layers, which cost more
        # than the node's work (an anchoring run is a few of these).
        selector, inputs, _outputs = self._function_types[function]
        call = _Calldata(self.address, selector + abi_encode(inputs, args))
        tx_hash = self._send(sender, call, label=function, gas=gas)
        with self._sent_lock:
            self._sent_functions[tx_hash] = function
            while len(self._sent_functions) > SENT_FUNCTIONS_KEPT:
                self._sent_functions.popitem(last=False)
        if not wait:
            return tx_hash
        return self._result(self.wait_for_receipt(tx_hash, function=function))

    def _reverted(
        self, exc: Exception, function: str | None, tx_hash: str | None = None
    ) -> TransactionReverted:
        if isinstance(exc, ContractPanicError):
            return TransactionReverted(
                "Panic", {"detail": str(exc.message)}, tx_hash=tx_hash, function=function
            )
        data = exc.data if isinstance(exc.data, str) else None
        return self._revert_decoded(data, exc.message, function, tx_hash)

    def _revert_decoded(
        self,
        data: str | bytes | None,
        message: str | None,
        function: str | None,
        tx_hash: str | None = None,
    ) -> TransactionReverted:
        """The contract's custom error from a revert's data, or the node's reason when the
        data names none."""
        name, args = self.artifact.decode_error(data)
        if name == "Reverted" and message:
            args = {"reason": message}
        return TransactionReverted(name, args, tx_hash=tx_hash, function=function)

    def _send(
        self,
        sender: LocalAccount,
        fn: Any,
        *,
        label: str,
        to: str | None = None,
        value: int = 0,
        attempts: int = 3,
        gas: int | None = None,
    ) -> str:
        """Sign and submit one transaction under the sender's nonce lock; return its hash.

        Gas is estimated before the lock is taken, so the lock is held only to choose the
        nonce, sign and hand the transaction to the node.
        """
        with _translated_errors(label):
            tx = self._build(sender, fn, to=to, value=value, label=label, gas=gas)
        with (
            _translated_errors(label),
            self.nonces.reserve(sender.address, self._pending_nonce) as slot,
        ):
            for attempt in range(1, attempts + 1):
                signed = sender.sign_transaction({**tx, "nonce": slot.nonce})
                slot.hold()
                try:
                    tx_hash = self._send_raw(signed.raw_transaction, label=label)
                except (NodeRefused, Web3RPCError, EthValidationError, ValueError) as exc:
                    message = str(exc)
                    if _ALREADY_KNOWN.search(message):
                        slot.commit()
                        return "0x" + bytes(signed.hash).hex()
                    if _INSUFFICIENT_FUNDS.search(message):
                        raise InsufficientFunds(f"{sender.address} cannot pay for {label}") from exc
                    if not _NONCE_ERROR.search(message):
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
                return "0x" + bytes(tx_hash).hex()
        raise AssertionError("unreachable")

    def _send_raw(self, raw: bytes, *, label: str) -> bytes:
        answer = self._rpc_lean("eth_sendRawTransaction", ["0x" + raw.hex()], label=label)
        return bytes(HexBytes(answer))

    def _pending_nonce(self, address: str) -> int:
        count = self._rpc_lean("eth_getTransactionCount", [address, "pending"], label="nonce")
        return int(count, 16)

    def _build(
        self,
        sender: LocalAccount,
        fn: Any,
        *,
        to: str | None,
        value: int,
        label: str,
        gas: int | None = None,
    ) -> dict[str, Any]:
        """The transaction without its nonce: gas estimated (unless given), fees filled."""
        params: dict[str, Any] = {"from": sender.address, "chainId": self.chain_id}
        if value:
            params["value"] = value
        try:
            if fn is None:
                params["to"] = to
                params["gas"] = 21_000
                tx = self._fill_fees(params)
            elif isinstance(fn, _Calldata):
                tx = self._build_lean(params, fn, label=label, gas=gas)
            else:
                # Estimated at zero fees: the gas does not depend on them, and a sender funded
                # for the gas it needs cannot cover a node's estimate at the block gas limit.
                if gas is None:
                    gas = int(fn.estimate_gas({**params, "gasPrice": 0}) * GAS_MARGIN)
                tx = fn.build_transaction(self._fill_fees({**params, "gas": gas}))
        except ContractLogicError as exc:
            raise self._reverted(exc, label) from exc
        except (Web3RPCError, EthValidationError, ValueError) as exc:
            if _INSUFFICIENT_FUNDS.search(str(exc)):
                raise InsufficientFunds(f"{sender.address} cannot pay for {label}") from exc
            raise
        return dict(tx)

    def _build_lean(
        self, params: dict[str, Any], call: _Calldata, *, label: str, gas: int | None
    ) -> dict[str, Any]:
        """`_build` for a real node: the gas estimate (unless given) and the fees asked in one
        JSON-RPC batch, the transaction written here."""
        data = "0x" + call.data.hex()
        requests_ = [
            ("eth_getBlockByNumber", ["latest", False]),
            ("eth_gasPrice", []),
            ("eth_maxPriorityFeePerGas", []),
        ]
        if gas is None:
            # At zero fees, as `_build` estimates: the gas does not depend on them.
            estimate = {"from": params["from"], "to": call.to, "data": data, "gasPrice": "0x0"}
            if params.get("value"):
                estimate["value"] = hex(params["value"])
            requests_.append(("eth_estimateGas", [estimate]))
        block, gas_price, tip, *estimated = self._rpc_lean_batch(requests_, label=label)
        for answer in (*estimated, block, gas_price):  # a refused estimate says why first
            if isinstance(answer, NodeRefused):
                raise self._refused(answer, label, sender=params["from"])
        if estimated:
            gas = int(int(estimated[0], 16) * GAS_MARGIN)
        base_fee = block.get("baseFeePerGas") if isinstance(block, dict) else None
        tx = {**params, "to": call.to, "data": data, "value": params.get("value", 0), "gas": gas}
        return self._fees(
            tx,
            base_fee=None if base_fee is None else int(base_fee, 16),
            gas_price=lambda: int(gas_price, 16),
            # A node without eth_maxPriorityFeePerGas: web3's estimate from the fee history.
            tip=lambda: (
                int(self.w3.eth.max_priority_fee) if isinstance(tip, NodeRefused) else int(tip, 16)
            ),
        )

    def _refused(self, refused: NodeRefused, label: str, *, sender: str) -> ChainError:
        """What a node's refusal to estimate or call means: the contract's revert (decoded),
        a sender who cannot pay, or the node's own refusal."""
        if _INSUFFICIENT_FUNDS.search(refused.message):
            return InsufficientFunds(f"{sender} cannot pay for {label}")
        data = HexBytes(refused.data) if refused.data else None
        if data and bytes(data[:4]) == _PANIC_SELECTOR:
            return TransactionReverted("Panic", {"detail": refused.message}, function=label)
        if data or "revert" in refused.message.lower():
            return self._revert_decoded(data, refused.message, label)
        return refused

    def _fill_fees(self, params: dict[str, Any]) -> dict[str, Any]:
        block = self.w3.eth.get_block("latest")
        base_fee = block.get("baseFeePerGas")
        return self._fees(
            params,
            base_fee=None if base_fee is None else int(base_fee),
            gas_price=lambda: int(self.w3.eth.gas_price),
            tip=lambda: int(self.w3.eth.max_priority_fee),
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

    def wait_for_receipt(
        self, tx_hash: str, *, timeout: float | None = None, function: str | None = None
    ) -> TxReceipt:
        """Wait for the receipt and the configured confirmations; raise if it reverted."""
        timeout = self.receipt_timeout if timeout is None else timeout
        deadline = time.monotonic() + timeout
        with _translated_errors(function):
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
        """The receipt from a real node, asked every poll_interval by lean requests (a receipt
        is formatted as web3 formats it once it is there). A node that cannot tell yet (geth
        while it indexes transactions) is asked again, as web3 does.

        Every DROPPED_CHECK_INTERVAL, and when the time is up, the node is asked whether it can
        still mine the transaction at all: one it lost, or holds behind a nonce gap, raises
        TransactionDropped at once instead of being waited for until the timeout."""
        checked = time.monotonic()
        while True:
            try:
                raw = self._rpc_lean("eth_getTransactionReceipt", [tx_hash], label="receipt")
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
        """Replay a failed transaction as a call to recover its custom error."""
        tx = self.w3.eth.get_transaction(HexBytes(tx_hash))
        call = {"from": tx["from"], "to": tx["to"], "data": tx["input"], "value": tx["value"]}
        try:
            self.w3.eth.call(call, block_identifier=int(receipt["blockNumber"]) - 1)
        except ContractLogicError as exc:
            return self._reverted(exc, function, tx_hash)
        except Web3RPCError:
            pass
        return TransactionReverted("Reverted", {}, tx_hash=tx_hash, function=function)

    def _result(self, receipt: TxReceipt) -> TxResult:
        return TxResult(
            tx_hash="0x" + bytes(receipt["transactionHash"]).hex(),
            block_number=int(receipt["blockNumber"]),
            gas_used=int(receipt["gasUsed"]),
            events=self.receipt_events(receipt),
        )

    def resync_nonce(self, address: str) -> None:
        """Forget our nonce counter for `address` (after a timeout or a dropped transaction)."""
        with _translated_errors():
            self.nonces.forget(address)


def _error_message(error: Any) -> str:
    return str(error.get("message", error)) if isinstance(error, dict) else str(error)


def _rpc_result(answer: Any, label: str) -> Any:
    """A JSON-RPC answer's result, or NodeRefused with its error's message and data."""
    error = answer.get("error") if isinstance(answer, dict) else "no answer"
    if error is not None:
        data = error.get("data") if isinstance(error, dict) else None
        raise NodeRefused(label, _error_message(error), data if isinstance(data, str) else None)
    return answer.get("result")


def _bytes32(value: bytes) -> bytes:
    if not isinstance(value, bytes | bytearray) or len(value) != 32:
        raise ValueError("expected 32 bytes")
    return bytes(value)
