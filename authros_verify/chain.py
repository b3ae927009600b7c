"""What the check asks the chain, through web3; each answer asked once per run."""

import functools
from dataclasses import dataclass
from typing import Any

import requests
from eth_abi import decode as abi_decode
from web3 import HTTPProvider, Web3
from web3.exceptions import ContractLogicError, TransactionNotFound, Web3Exception

from authros_verify.abi import (
    ABI,
    DATA_UPLOADED,
    ROBOT_KEY_ADDED,
    ROBOT_KEY_REVOKED,
    ROOT_ANCHORED,
    event_topic,
)


class ChainUnreachable(Exception):
    """The node cannot be asked (down, refused, not a node)."""


@dataclass(frozen=True)
class AnchoredRoot:
    size: int
    time: int
    block: int


@dataclass(frozen=True)
class AnchoredRecord:
    owner: str
    digest: bytes


@dataclass(frozen=True)
class RobotKey:
    """A robot's signing key as the contract holds it for one owner (robotKeyOfOwner) or for
    its first owner (robotKeyOf): the EOA that added it (None: never added), the block it was
    added in, the block it was revoked in (None: live)."""

    owner: str | None
    added_block: int
    revoked_block: int | None

    def live_at(self, block: int) -> bool:
        """Whether the key counts for what was anchored in `block` (DESIGN.md "A record is
        genuine"): added at or before it, and not revoked by then."""
        return (
            self.owner is not None
            and self.added_block <= block
            and (self.revoked_block is None or block < self.revoked_block)
        )


@dataclass(frozen=True)
class RobotKeyEvent:
    """One RobotKeyAdded (with the public key x||y it registered) or RobotKeyRevoked log."""

    kind: str  # "added" or "revoked"
    key_hash: bytes
    public_key: bytes | None
    block: int
    log_index: int
    tx: str


@dataclass(frozen=True)
class Receipt:
    status: int
    block: int
    to: str | None
    # (emitting contract, topics, data) of each log
    logs: tuple[tuple[str, tuple[bytes, ...], bytes], ...]

    def root_anchored(self, contract: str, sender: str, root: bytes) -> int | None:
        """The size a RootAnchored(sender, root) of `contract` in this receipt states."""
        for size, *_ in self._events(contract, ROOT_ANCHORED, _address_topic(sender), root):
            return int(size)
        return None

    def data_uploaded(self, contract: str, record_id: bytes, owner: str) -> bytes | None:
        """The digest a DataUploaded(record id, owner) of `contract` in this receipt states."""
        for digest, *_ in self._events(contract, DATA_UPLOADED, record_id, _address_topic(owner)):
            return bytes(digest)
        return None

    def _events(self, contract: str, event: dict, *indexed: bytes) -> tuple[tuple, ...]:
        data_types = tuple(item["type"] for item in event["inputs"] if not item["indexed"])
        topic = _TOPICS.get(event["name"]) or _TOPICS.setdefault(event["name"], event_topic(event))
        return _events_decoded(self.logs, contract.lower(), data_types, topic, indexed)


_TOPICS: dict[str, bytes] = {}  # topic[0] of each event, by name: keccak once per event


# A receipt's logs decoded once for all the records anchored by its transaction (a tree's
# records share it): a pure function of the chain's answer, never of a verdict.
@functools.lru_cache(maxsize=1024)
def _events_decoded(
    logs: tuple[tuple[str, tuple[bytes, ...], bytes], ...],
    contract: str,
    data_types: tuple[str, ...],
    topic: bytes,
    indexed: tuple[bytes, ...],
) -> tuple[tuple, ...]:
    wanted = (topic, *indexed)
    return tuple(
        abi_decode(list(data_types), data)
        for address, topics, data in logs
        if address.lower() == contract and topics == wanted
    )


# An address's checksummed spelling (keccak of it) once per spelling, not once per record: an
# export's records name a few owners.
@functools.lru_cache(maxsize=256)
def _checksummed(address: str) -> str:
    return Web3.to_checksum_address(address)


def _address_topic(address: str) -> bytes:
    return bytes(12) + bytes.fromhex(address.removeprefix("0x"))


def _topic_hex(address: str) -> str:
    return "0x" + _address_topic(address).hex()


class ChainReader:
    """Reads of one chain; `w3` is any Web3 (an HTTP node, or an in-process one in tests)."""

    def __init__(self, w3: Web3) -> None:
        self.w3 = w3
        self._cache: dict[tuple, Any] = {}

    @classmethod
    def from_url(cls, url: str, *, timeout: float = 30.0) -> "ChainReader":
        provider = Web3.HTTPProvider(
            url, request_kwargs={"timeout": timeout}, session=requests.Session()
        )
        return cls(Web3(provider))

    def forked(self) -> "ChainReader":
        """The reader for a forked process: the answers read so far, and for a node over HTTP
        a connection of its own (a connection shared with the parent would mix answers)."""
        provider = self.w3.provider
        if not isinstance(provider, HTTPProvider):
            return self  # in-process: the fork's copy is its own
        own = HTTPProvider(
            provider.endpoint_uri,
            request_kwargs=dict(provider.get_request_kwargs()),
            session=requests.Session(),
        )
        reader = ChainReader(Web3(own))
        reader._cache = dict(self._cache)
        return reader

    def chain_id(self) -> int:
        return self._once(("chain_id",), lambda: int(self.w3.eth.chain_id))

    def has_code(self, contract: str) -> bool:
        return self._once(("code", contract), lambda: len(self.w3.eth.get_code(contract)) > 0)

    def root_of(self, contract: str, sender: str, root: bytes) -> AnchoredRoot:
        def ask() -> AnchoredRoot:
            size, when, block = self._contract(contract).functions.rootOf(sender, root).call()
            return AnchoredRoot(int(size), int(when), int(block))

        return self._once(("rootOf", contract, sender, root), ask)

    def data_query(self, contract: str, record_id: bytes, *, owner: str) -> AnchoredRecord:
        """`owner`'s record under the id (dataQueryOf: ids are bound to their owner)."""

        def ask() -> AnchoredRecord:
            found, digest, _when, _type = (
                self._contract(contract)
                .functions.dataQueryOf(Web3.to_checksum_address(owner), record_id)
                .call()
            )
            return AnchoredRecord(str(found), bytes(digest))

        return self._once(("dataQueryOf", contract, owner, record_id), ask)

    def robot_key_of(self, contract: str, key_hash: bytes) -> RobotKey:
        def ask() -> RobotKey:
            owner, added, revoked = self._contract(contract).functions.robotKeyOf(key_hash).call()
            return RobotKey(
                None if int(owner, 16) == 0 else str(owner), int(added), int(revoked) or None
            )

        return self._once(("robotKeyOf", contract, key_hash), ask)

    def robot_key_of_owner(self, contract: str, owner: str, key_hash: bytes) -> RobotKey:
        """The key as `owner` registered it (robotKeyOfOwner): owner None if `owner` never
        added it, whoever else did. A contract from before per-owner keys has robotKeyOf
        alone: its answer then, when it names `owner`."""
        owner = _checksummed(owner)

        def ask() -> RobotKey:
            functions = self._contract(contract).functions
            try:
                added, revoked = functions.robotKeyOfOwner(owner, key_hash).call()
            except ContractLogicError:  # no such function in that deployment
                first = self.robot_key_of(contract, key_hash)
                named = first.owner is not None and first.owner.lower() == owner.lower()
                return first if named else RobotKey(None, 0, None)
            return RobotKey(owner if int(added) else None, int(added), int(revoked) or None)

        return self._once(("robotKeyOfOwner", contract, owner, key_hash), ask)

    def robot_key_events(
        self, contract: str, owner: str, *, from_block: int = 0
    ) -> list[RobotKeyEvent]:
        """Every RobotKeyAdded and RobotKeyRevoked the contract logged for `owner` (its
        first indexed topic), in chain order: one log query, no contract state."""
        added, revoked = event_topic(ROBOT_KEY_ADDED), event_topic(ROBOT_KEY_REVOKED)

        def ask() -> list[RobotKeyEvent]:
            logs = self.w3.eth.get_logs(
                {
                    "address": contract,
                    "fromBlock": from_block,
                    "toBlock": "latest",
                    "topics": [["0x" + added.hex(), "0x" + revoked.hex()], _topic_hex(owner)],
                }
            )
            events = []
            for log in logs:
                topics = [bytes(topic) for topic in log["topics"]]
                if len(topics) != 3 or topics[0] not in (added, revoked):
                    continue
                public_key = None
                if topics[0] == added:
                    (public_key,) = abi_decode(["bytes"], bytes(log["data"]))
                tx = log["transactionHash"]
                events.append(
                    RobotKeyEvent(
                        kind="added" if topics[0] == added else "revoked",
                        key_hash=topics[2],
                        public_key=None if public_key is None else bytes(public_key),
                        block=int(log["blockNumber"]),
                        log_index=int(log["logIndex"]),
                        tx=tx if isinstance(tx, str) else "0x" + bytes(tx).hex(),
                    )
                )
            return sorted(events, key=lambda event: (event.block, event.log_index))

        return self._once(("robotKeyEvents", contract, owner, from_block), ask)

    def receipt(self, tx: str) -> Receipt | None:
        def ask() -> Receipt | None:
            try:
                answer = self.w3.eth.get_transaction_receipt(tx)
            except TransactionNotFound:
                return None
            logs = tuple(
                (str(log["address"]), tuple(bytes(t) for t in log["topics"]), bytes(log["data"]))
                for log in answer["logs"]
            )
            return Receipt(int(answer["status"]), int(answer["blockNumber"]), answer["to"], logs)

        return self._once(("receipt", tx), ask)

    def _contract(self, address: str) -> Any:
        return self.w3.eth.contract(address=address, abi=ABI)

    def _once(self, key: tuple, ask: Any) -> Any:
        if key not in self._cache:
            try:
                self._cache[key] = ask()
            except (requests.ConnectionError, requests.Timeout, OSError) as exc:
                raise ChainUnreachable(f"the chain node cannot be reached: {exc}") from exc
            except Web3Exception as exc:
                raise ChainUnreachable(f"the chain node refused a read: {exc}") from exc
        return self._cache[key]
