"""The one client of the AuthROS contract: its functions by name, as typed methods.

`AuthROSChain` connects to a node by its JSON-RPC URL (``http(s)://``: geth, anvil, a PoA
network; the tests run one anvil per session), deploys or loads the contract, and wraps each
contract function as a method. Every read is one eth_call encoded and decoded here (`_read`,
through `chainworker.rpc.NodeRpc`); every write one transaction sent by
`chainworker.sender.TransactionSender`, the client's base, signed locally by the sending
account with nonces from `chainworker.nonces`, so any number of processes may send. Events are
read from the node's logs, filtered by topic there. This module does not import Django:
`chainworker.services.chain_client()` builds the client from settings.

A little over 500 lines: one short method for each of the contract's functions and event
queries, which would read worse split apart; what they build on is in the modules above.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from functools import cached_property
from typing import Any

import redis
from eth_account.signers.local import LocalAccount
from hexbytes import HexBytes
from web3 import Web3
from web3.types import TxReceipt

from chainworker.codec import (
    ZERO_ADDRESS,
    AnchorItem,
    ChainEvent,
    ContractArtifact,
    OnChainGrant,
    OnChainRecord,
    OnChainRoot,
    RobotKeyOnChain,
    TxResult,
    bytes32,
    bytes32_to_data_type,
    chain_time_to_datetime,
    record_id_to_bytes32,
)
from chainworker.errors import (
    ChainError,
    ChainUnavailable,
    ContractNotDeployed,
    NodeRefused,
    refusal_explained,
    translated_errors,
)
from chainworker.sender import TRANSFER_GAS, TransactionSender
from smcrypto.sm3 import sm3_digest

# Gas for anchorRoot sent without an estimate (a root following one in flight): a sender's
# first root takes about 70,000, the next ones about 55,000, whatever the tree's size.
ANCHOR_ROOT_GAS = 120_000
# A robot's SM2 public key as robotKeyAdd takes it: x||y, without the 04 marker.
ROBOT_PUBLIC_KEY_LENGTH = 64


class AuthROSChain(TransactionSender):
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
        super().__init__(
            url,
            redis_client=redis_client,
            artifact=artifact or ContractArtifact.load(),
            receipt_timeout=receipt_timeout,
            rpc_timeout=rpc_timeout,
            confirmations=confirmations,
            poll_interval=poll_interval,
            redis_prefix=redis_prefix,
            nonce_lock_timeout=nonce_lock_timeout,
        )
        self._address: str | None = None
        self._contract: Any = None
        # (contract address, view function) -> whether that deployment has it
        self._functions: dict[tuple[str, str], bool] = {}
        if contract_address:
            self.use_contract(contract_address)

    # the node -------------------------------------------------------------------------

    @cached_property
    def client_version(self) -> str:
        with translated_errors():
            return str(self.w3.client_version)

    def latest_block(self) -> int:
        with translated_errors():
            return int(self.w3.eth.block_number)

    def balance(self, address: str) -> int:
        with translated_errors():
            return int(self.w3.eth.get_balance(Web3.to_checksum_address(address)))

    def is_connected(self) -> bool:
        try:
            self.latest_block()
        except ChainUnavailable:
            return False
        return True

    def head(self) -> tuple[int, int]:
        """The latest block's number and timestamp (seconds since the epoch)."""
        with translated_errors():
            block = self.w3.eth.get_block("latest")
        return int(block["number"]), int(block["timestamp"])

    def pending_transaction_count(self) -> int | None:
        """Transactions the node holds ready to mine and has not mined: txpool_status's
        "pending" (anvil, geth, Nethermind), else the pending block's; None if it tells neither."""
        with translated_errors():
            status = self.w3.provider.make_request("txpool_status", []).get("result")
            if isinstance(status, dict) and "pending" in status:
                return int(str(status["pending"]), 0)
            pending = self.w3.provider.make_request("eth_getBlockByNumber", ["pending", False])
        block = pending.get("result")
        return len(block.get("transactions") or []) if isinstance(block, dict) else None

    def has_code(self, address: str) -> bool:
        with translated_errors():
            return len(self.w3.eth.get_code(Web3.to_checksum_address(address))) > 0

    def dev_faucet(self, address: str, value_wei: int) -> bool:
        """Give `address` at least `value_wei` on a development chain; False on a real one."""
        address = Web3.to_checksum_address(address)
        with translated_errors():
            if self.client_version.lower().startswith("anvil"):
                target = self.balance(address) + value_wei
                self.w3.provider.make_request("anvil_setBalance", [address, hex(target)])
                return True
        return False

    # contract -------------------------------------------------------------------------

    @property
    def address(self) -> str:
        if self._address is None:
            raise ContractNotDeployed("no AuthROS contract address is set for this chain")
        return self._address

    @property
    def contract(self) -> Any:
        """The web3 contract at `address` (the client decodes its events with it)."""
        if self._contract is None:
            raise ContractNotDeployed("no AuthROS contract address is set for this chain")
        return self._contract

    def use_contract(self, address: str) -> None:
        self._address = Web3.to_checksum_address(address)
        self._contract = self.w3.eth.contract(address=self._address, abi=self.artifact.abi)

    def deploy(self, deployer: LocalAccount) -> TxResult:
        """Deploy a new AuthROS contract (admin = deployer) and start using it."""
        bytecode = bytes(HexBytes(self.artifact.bytecode))
        tx_hash = self.send(deployer, label="deploy", to=None, data=bytecode)
        receipt = self.wait_for_receipt(tx_hash)
        self.use_contract(receipt["contractAddress"])
        return self._result(receipt)

    def admin(self) -> str:
        return self._read("admin")[0]

    # writes ---------------------------------------------------------------------------

    def enroll(self, admin: LocalAccount, eoa: str, *, wait: bool = True) -> TxResult | str:
        return self._transact(admin, "enroll", Web3.to_checksum_address(eoa), wait=wait)

    def register(
        self, owner: LocalAccount, commitment: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "register", bytes32(commitment), wait=wait)

    def rotate_key(
        self, owner: LocalAccount, commitment: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(owner, "rotateKey", bytes32(commitment), wait=wait)

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
        args = (bytes32(root), size, bytes32(prev_root))
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
            bytes32(scope),
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
        if sm3_digest(bytes(public_key)) != bytes32(key_hash):
            raise ValueError("key_hash is not SM3 of public_key")
        return self._transact(sender, "robotKeyAdd", bytes(key_hash), bytes(public_key), wait=wait)

    def robot_key_revoke(
        self, sender: LocalAccount, key_hash: bytes, *, wait: bool = True
    ) -> TxResult | str:
        return self._transact(sender, "robotKeyRevoke", bytes32(key_hash), wait=wait)

    def transfer(
        self, sender: LocalAccount, to: str, value_wei: int, *, wait: bool = True
    ) -> TxResult | str:
        """Plain value transfer, e.g. the operator funding a new custodial EOA."""
        tx_hash = self.send(
            sender,
            label="transfer",
            to=Web3.to_checksum_address(to),
            value=value_wei,
            gas=TRANSFER_GAS,
        )
        return self._result(self.wait_for_receipt(tx_hash)) if wait else tx_hash

    # reads ----------------------------------------------------------------------------

    def data_query(self, record_id: uuid.UUID | str, *, owner: str) -> OnChainRecord | None:
        """`owner`'s anchored record under this id, or None if it has none yet (record ids are
        bound to their owner on chain: another account's record under the id is not this)."""
        owner, digest, when, data_type = self._read(
            "dataQueryOf", Web3.to_checksum_address(owner), record_id_to_bytes32(record_id)
        )
        if int(owner, 16) == 0:
            return None
        return OnChainRecord(
            record_id=uuid.UUID(str(record_id)),
            owner=owner,
            digest=bytes(digest),
            time=chain_time_to_datetime(when),
            data_type=bytes32_to_data_type(data_type),
        )

    def data_check(self, record_id: uuid.UUID | str, digest: bytes, *, owner: str) -> bool:
        (matches,) = self._read(
            "dataCheckOf",
            Web3.to_checksum_address(owner),
            record_id_to_bytes32(record_id),
            bytes32(digest),
        )
        return bool(matches)

    def root_of(self, sender: str, root: bytes) -> OnChainRoot | None:
        """The root as `sender` anchored it, or None if it never did (on this chain)."""
        size, when, block = self._read("rootOf", Web3.to_checksum_address(sender), bytes32(root))
        if int(size) == 0:
            return None
        return OnChainRoot(
            sender=Web3.to_checksum_address(sender),
            root=bytes(root),
            size=int(size),
            time=chain_time_to_datetime(when),
            block_number=int(block),
        )

    def last_root_of(self, sender: str) -> bytes:
        """The last root `sender` anchored (zeros before its first)."""
        return bytes(self._read("lastRootOf", Web3.to_checksum_address(sender))[0])

    def robot_key_of(self, key_hash: bytes) -> RobotKeyOnChain:
        """A robot key by its hash as its first owner registered it (robotKeyOf); owner None
        when no EOA ever added it. Checks ask robot_key_of_owner, with the record's owner."""
        owner, added, revoked = self._read("robotKeyOf", bytes32(key_hash))
        return RobotKeyOnChain(
            owner=None if int(owner, 16) == 0 else owner,
            added_block=int(added),
            revoked_block=int(revoked) or None,
        )

    def robot_key_of_owner(self, key_hash: bytes, *, owner: str) -> RobotKeyOnChain:
        """A robot key as `owner` registered it (robotKeyOfOwner: the check of every signed
        record, asked with the record's owner); owner None when `owner` never added it,
        whoever else did. On a deployment from before per-owner keys, robotKeyOf's answer
        when it names `owner`."""
        owner = Web3.to_checksum_address(owner)
        if not self.has_owner_robot_keys():
            first = self.robot_key_of(key_hash)
            if first.owner is not None and first.owner.lower() == owner.lower():
                return first
            return RobotKeyOnChain(owner=None, added_block=0, revoked_block=None)
        added, revoked = self._read("robotKeyOfOwner", owner, bytes32(key_hash))
        return RobotKeyOnChain(
            owner=owner if int(added) else None,
            added_block=int(added),
            revoked_block=int(revoked) or None,
        )

    def has_access(self, owner: str, viewer: str) -> bool:
        (access,) = self._read(
            "hasAccess", Web3.to_checksum_address(owner), Web3.to_checksum_address(viewer)
        )
        return bool(access)

    def grant_of(self, owner: str, grantee: str) -> OnChainGrant | None:
        """The grant from `owner` to `grantee` in one eth_call (the check at view); None when
        the contract in use predates scoped grants (no grantOf: see has_scoped_grants)."""
        if not self.has_scoped_grants():
            return None
        live, scope, expiry = self._read(
            "grantOf", Web3.to_checksum_address(owner), Web3.to_checksum_address(grantee)
        )
        return OnChainGrant(live=bool(live), scope=bytes(scope), expiry=int(expiry))

    def has_scoped_grants(self) -> bool:
        """Whether the contract in use has grantOf and authorityGrantScoped: a deployment made
        before them has not (docs/grants.md says how to upgrade). Asked once per address."""
        return self._has_function("grantOf", ZERO_ADDRESS, ZERO_ADDRESS)

    def has_owner_robot_keys(self) -> bool:
        """Whether the contract in use keeps robot keys per owner (robotKeyOfOwner): a
        deployment made before issue 46 has robotKeyOf alone. Asked once per address."""
        return self._has_function("robotKeyOfOwner", ZERO_ADDRESS, bytes(32))

    def _has_function(self, function: str, *probe: Any) -> bool:
        """Whether the view `function` answers `probe` on the contract in use (the code of an
        older deployment reverts: no such function); asked once per address."""
        wanted = (self.address, function)
        if wanted not in self._functions:
            try:
                self._read(function, *probe)
            except (ChainUnavailable, ContractNotDeployed):
                raise
            except ChainError:  # the old code reverts: no such function
                self._functions[wanted] = False
            else:
                self._functions[wanted] = True
        return self._functions[wanted]

    def is_enrolled(self, eoa: str) -> bool:
        return bool(self._read("isEnrolled", Web3.to_checksum_address(eoa))[0])

    def is_registered(self, eoa: str) -> bool:
        return bool(self._read("isRegistered", Web3.to_checksum_address(eoa))[0])

    def commitment_of(self, eoa: str) -> bytes:
        """The owner's key commitment (the identity check of uploads and views)."""
        (commitment,) = self._read("commitmentOf", Web3.to_checksum_address(eoa))
        return bytes(commitment)

    def record_count(self) -> int:
        return int(self._read("recordCount")[0])

    # events ---------------------------------------------------------------------------

    def events(
        self,
        from_block: int = 0,
        to_block: int | str = "latest",
        *,
        names: Sequence[str] | None = None,
    ) -> list[ChainEvent]:
        """Decoded contract events in a block range, oldest first."""
        with translated_errors():
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
            indexed = self.artifact.indexed_arguments[name]
            for argument in names:
                if argument not in indexed:
                    raise ValueError(f"{name}.{argument} is not an indexed argument")
                topic = "0x" + self.artifact.topic_by_event[name].hex()
                by_position.setdefault(indexed.index(argument) + 1, []).append(topic)
        logs: dict[tuple[int, int], Any] = {}
        with translated_errors():
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

    def upload_event(self, record_id: uuid.UUID | str, *, owner: str) -> ChainEvent | None:
        """The DataUploaded event of `owner`'s record (its transaction and block), if anchored."""
        owner_word = Web3.to_checksum_address(owner).lower().removeprefix("0x").rjust(64, "0")
        return self._event_by_topics(
            "DataUploaded", ["0x" + record_id_to_bytes32(record_id).hex(), "0x" + owner_word]
        )

    def root_event(self, sender: str, root: bytes) -> ChainEvent | None:
        """The RootAnchored event of a sender's root (its transaction and block), if the node
        still holds it."""
        sender_word = Web3.to_checksum_address(sender).lower().removeprefix("0x").rjust(64, "0")
        return self._event_by_topics(
            "RootAnchored", ["0x" + sender_word, "0x" + bytes32(root).hex()]
        )

    def receipt_events(self, receipt: TxReceipt) -> list[ChainEvent]:
        if self._address is None:
            return []
        return [
            event
            for log in receipt["logs"]
            if log["address"].lower() == self.address.lower()
            and (event := self._decode_log(log)) is not None
        ]

    # internals ------------------------------------------------------------------------

    def _read(self, function: str, *args: Any) -> tuple[Any, ...]:
        """One eth_call of the view `function`: the calldata encoded here, sent by the provider
        itself and its answer decoded here, past web3's contract and middleware layers, which
        cost more than the request (see chainworker/rpc.py). Always a tuple of the function's
        outputs, addresses checksummed; the contract's refusal is TransactionReverted."""
        call = {"to": self.address, "data": "0x" + self.artifact.calldata(function, args).hex()}
        try:
            result = self.rpc.call(call, label=function)
        except NodeRefused as refused:
            explained = refusal_explained(refused, artifact=self.artifact, label=function)
            if explained is refused:
                raise
            raise explained from refused
        if not result:
            # An empty answer: no code at the address (a reset chain), not a crash.
            raise ContractNotDeployed(f"{function}: no contract at {self._address}")
        return self.artifact.outputs_decoded(function, result)

    def _transact(
        self, sender: LocalAccount, function: str, *args: Any, wait: bool, gas: int | None = None
    ) -> TxResult | str:
        data = self.artifact.calldata(function, args)
        tx_hash = self.send(
            sender, label=function, to=self.address, data=data, gas=gas, function=function
        )
        if not wait:
            return tx_hash
        return self._result(self.wait_for_receipt(tx_hash, function=function))

    def _result(self, receipt: TxReceipt) -> TxResult:
        return TxResult(
            tx_hash="0x" + bytes(receipt["transactionHash"]).hex(),
            block_number=int(receipt["blockNumber"]),
            gas_used=int(receipt["gasUsed"]),
            events=self.receipt_events(receipt),
        )

    def _event_by_topics(self, name: str, topics: list[str]) -> ChainEvent | None:
        """The first event `name` whose indexed arguments are `topics`, over the whole chain."""
        signature = "0x" + self.artifact.topic_by_event[name].hex()
        with translated_errors():
            logs = self.w3.eth.get_logs(
                {
                    "address": self.address,
                    "fromBlock": 0,
                    "toBlock": "latest",
                    "topics": [signature, *topics],
                }
            )
        events = [event for log in logs if (event := self._decode_log(log)) is not None]
        return events[0] if events else None

    def _decode_log(self, log: Any) -> ChainEvent | None:
        if not log["topics"]:
            return None
        name = self.artifact.event_by_topic.get(bytes(log["topics"][0]))
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
