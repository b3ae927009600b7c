"""Values as the AuthROS contract holds them, and the contract's ABI as bytes.

The conversions between the portal's values and the contract's words (a record id, a ROS
type, a capture time as bytes32 or microseconds), the results the client hands back (events,
mined transactions, records, roots, grants and robot keys as the contract holds them), and
`ContractArtifact`: the compiled contract, which encodes a function's calldata, decodes its
outputs, its custom errors and its events' topics. Everything here is pure: no node, no
Django.
"""

from __future__ import annotations

import json
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path
from typing import Any

from eth_abi import decode as abi_decode
from eth_abi import encode as abi_encode
from eth_utils import event_abi_to_log_topic, function_abi_to_4byte_selector, keccak
from hexbytes import HexBytes
from web3 import Web3

ARTIFACT_PATH = Path(__file__).resolve().parent.parent / "contracts" / "build" / "AuthROS.json"
ZERO_ADDRESS = "0x" + "00" * 20
ZERO_BYTES32 = b"\x00" * 32
# Revert data of a Solidity panic (assert, overflow): Panic(uint256).
PANIC_SELECTOR = bytes.fromhex("4e487b71")


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


def bytes32(value: bytes) -> bytes:
    """`value` as a bytes32 argument: exactly 32 bytes, else ValueError."""
    if not isinstance(value, bytes | bytearray) or len(value) != 32:
        raise ValueError("expected 32 bytes")
    return bytes(value)


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
    """A robot's signing key as the contract holds it (robotKeyOfOwner, or robotKeyOf for its
    first owner): the EOA that added it (None: never added), the block it was added in and
    the block it was revoked in (None: live)."""

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


# --- the contract's ABI --------------------------------------------------------------------


@dataclass(frozen=True)
class ContractArtifact:
    """The compiled contract (contracts/build/AuthROS.json): its ABI and bytecode."""

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

    # functions ------------------------------------------------------------------------

    @cached_property
    def function_types(self) -> dict[str, tuple[bytes, list[str], list[str]]]:
        """Each contract function's selector, input types and output types."""
        return {
            entry["name"]: (
                function_abi_to_4byte_selector(entry),
                [item["type"] for item in entry["inputs"]],
                [item["type"] for item in entry["outputs"]],
            )
            for entry in self.abi
            if entry.get("type") == "function"
        }

    def calldata(self, function: str, args: tuple[Any, ...]) -> bytes:
        """A call of `function` with `args`: its selector and ABI-encoded arguments."""
        selector, inputs, _outputs = self.function_types[function]
        return selector + abi_encode(inputs, args)

    def outputs_decoded(self, function: str, data: bytes) -> tuple[Any, ...]:
        """`function`'s outputs from the bytes an eth_call answered, always a tuple; addresses
        checksummed, as web3 hands them."""
        _selector, _inputs, outputs = self.function_types[function]
        values = abi_decode(outputs, data)
        return tuple(
            Web3.to_checksum_address(value) if kind == "address" else value
            for kind, value in zip(outputs, values, strict=True)
        )

    # errors ---------------------------------------------------------------------------

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

    # events ---------------------------------------------------------------------------

    @cached_property
    def topic_by_event(self) -> dict[str, bytes]:
        """Each event's signature topic (topic 0 of its logs)."""
        return {
            entry["name"]: bytes(event_abi_to_log_topic(entry))
            for entry in self.abi
            if entry.get("type") == "event"
        }

    @cached_property
    def event_by_topic(self) -> dict[bytes, str]:
        return {topic: name for name, topic in self.topic_by_event.items()}

    @cached_property
    def indexed_arguments(self) -> dict[str, list[str]]:
        """Each event's indexed argument names, in topic order (topic 0 is the signature)."""
        return {
            entry["name"]: [arg["name"] for arg in entry["inputs"] if arg.get("indexed")]
            for entry in self.abi
            if entry.get("type") == "event"
        }
