"""Robot signing keys through the chain client (robot_key_add, robot_key_revoke,
robot_key_of), against the session's anvil over the JSON-RPC path production runs."""

import dataclasses
import json
from pathlib import Path

import pytest
from eth_account import Account
from web3 import Web3

from authros_verify.chain import ChainReader, RobotKey
from chainworker.codec import RobotKeyOnChain
from chainworker.errors import TransactionReverted
from smcrypto import sm2, sm3
from tests.support.chain_setup import make_registered_owner

ROBOT_KEY_EVENTS = {"RobotKeyAdded": ("owner",), "RobotKeyRevoked": ("owner",)}


def _robot_key() -> tuple[bytes, bytes]:
    """(key hash, public key x||y) of a new robot, as DESIGN.md "Provenance" defines them."""
    _private, public = sm2.generate_keypair()
    public_key = bytes.fromhex(public)[1:]  # 04||x||y -> x||y
    return sm3.sm3_digest(public_key), public_key


def _refusal(call, *args) -> TransactionReverted:
    with pytest.raises(TransactionReverted) as refused:
        call(*args)
    return refused.value


def test_live_at_is_added_at_or_before_and_not_revoked_by_then():
    live = RobotKeyOnChain(owner="0x" + "11" * 20, added_block=10, revoked_block=None)
    revoked = dataclasses.replace(live, revoked_block=20)
    unknown = RobotKeyOnChain(owner=None, added_block=0, revoked_block=None)

    assert [live.live_at(block) for block in (9, 10, 11, 10**9)] == [False, True, True, True]
    assert [revoked.live_at(block) for block in (9, 10, 19, 20, 21)] == [
        False,
        True,
        True,
        False,
        False,
    ]
    assert [unknown.live_at(block) for block in (0, 1, 10**9)] == [False, False, False]
    with pytest.raises(dataclasses.FrozenInstanceError):
        live.revoked_block = 1  # type: ignore[misc]


def test_add_query_and_revoke(chain, registered_owner):
    key_hash, public_key = _robot_key()
    assert chain.robot_key_of(key_hash) == RobotKeyOnChain(None, 0, None)

    added = chain.robot_key_add(registered_owner, key_hash, public_key)

    assert [(e.name, e.args) for e in added.events] == [
        (
            "RobotKeyAdded",
            {"owner": registered_owner.address, "keyHash": key_hash, "publicKey": public_key},
        )
    ]
    key = chain.robot_key_of(key_hash)
    assert key == RobotKeyOnChain(registered_owner.address, added.block_number, None)
    assert key.live_at(added.block_number)
    assert not key.live_at(added.block_number - 1)

    revoked = chain.robot_key_revoke(registered_owner, key_hash)

    assert [(e.name, e.args) for e in revoked.events] == [
        ("RobotKeyRevoked", {"owner": registered_owner.address, "keyHash": key_hash})
    ]
    key = chain.robot_key_of(key_hash)
    assert key == RobotKeyOnChain(
        registered_owner.address, added.block_number, revoked.block_number
    )
    assert key.live_at(revoked.block_number - 1)
    assert not key.live_at(revoked.block_number)


def test_send_without_waiting_then_wait(chain, registered_owner):
    key_hash, public_key = _robot_key()
    tx_hash = chain.robot_key_add(registered_owner, key_hash, public_key, wait=False)
    assert tx_hash.startswith("0x")
    receipt = chain.wait_for_receipt(tx_hash)
    assert receipt["status"] == 1
    assert chain.robot_key_of(key_hash).added_block == receipt["blockNumber"]


def test_refusals_carry_the_custom_error_name(chain, operator, registered_owner):
    other = make_registered_owner(chain, operator)
    stranger = Account.create()
    chain.transfer(operator, stranger.address, 10**18)
    key_hash, public_key = _robot_key()
    unknown_hash, _ = _robot_key()

    refused = _refusal(chain.robot_key_add, stranger, key_hash, public_key)
    assert (refused.error_name, refused.error_args) == (
        "NotRegistered",
        {"caller": stranger.address},
    )
    assert "robotKeyAdd" in str(refused)

    chain.robot_key_add(registered_owner, key_hash, public_key)
    refused = _refusal(chain.robot_key_add, registered_owner, key_hash, public_key)
    assert (refused.error_name, refused.error_args) == ("RobotKeyExists", {"keyHash": key_hash})

    refused = _refusal(chain.robot_key_revoke, registered_owner, unknown_hash)
    assert (refused.error_name, refused.error_args) == (
        "RobotKeyUnknown",
        {"keyHash": unknown_hash},
    )
    # Keys are kept per owner: another EOA has none of its own to revoke.
    refused = _refusal(chain.robot_key_revoke, other, key_hash)
    assert (refused.error_name, refused.error_args) == ("RobotKeyUnknown", {"keyHash": key_hash})

    chain.robot_key_revoke(registered_owner, key_hash)
    refused = _refusal(chain.robot_key_revoke, registered_owner, key_hash)
    assert (refused.error_name, refused.error_args) == (
        "RobotKeyAlreadyRevoked",
        {"keyHash": key_hash},
    )
    refused = _refusal(chain.robot_key_add, registered_owner, key_hash, public_key)
    assert refused.error_name == "RobotKeyExists"  # a revoked key never comes back


def test_keys_are_read_as_each_owner_registered_them(chain, operator, registered_owner):
    """robot_key_of_owner answers for one owner (robotKeyOfOwner, what every check asks);
    robot_key_of names the first owner, whoever registered the key after it."""
    other = make_registered_owner(chain, operator)
    key_hash, public_key = _robot_key()
    assert chain.has_owner_robot_keys()
    first = chain.robot_key_add(other, key_hash, public_key)

    mine = chain.robot_key_add(registered_owner, key_hash, public_key)

    assert chain.robot_key_of_owner(key_hash, owner=registered_owner.address) == (
        RobotKeyOnChain(registered_owner.address, mine.block_number, None)
    )
    assert chain.robot_key_of_owner(key_hash, owner=other.address) == (
        RobotKeyOnChain(other.address, first.block_number, None)
    )
    assert chain.robot_key_of(key_hash) == RobotKeyOnChain(other.address, first.block_number, None)
    revoked = chain.robot_key_revoke(registered_owner, key_hash)
    assert chain.robot_key_of_owner(key_hash, owner=registered_owner.address).revoked_block == (
        revoked.block_number
    )
    assert chain.robot_key_of(key_hash).revoked_block is None  # the first owner's is live
    stranger = Account.create().address
    assert chain.robot_key_of_owner(key_hash, owner=stranger) == RobotKeyOnChain(None, 0, None)


# The bytecode of contracts/build/AuthROS.json before per-owner robot keys (robotKeyOf alone).
DEPLOYMENT_BEFORE_ISSUE_46 = (
    Path(__file__).parents[1] / "support/AuthROS-before-robot-key-owners.json"
)


def test_a_deployment_from_before_per_owner_keys_is_read_through_robot_key_of(chain, operator):
    """A network that still runs the older contract: the client and authros-verify find no
    robotKeyOfOwner and read robotKeyOf, which counts for the owner it names only."""
    bytecode = json.loads(DEPLOYMENT_BEFORE_ISSUE_46.read_text())["bytecode"]
    deployed = chain.wait_for_receipt(
        chain.send(operator, label="deploy", to=None, data=bytes.fromhex(bytecode[2:]))
    )
    chain.use_contract(deployed["contractAddress"])
    owner, other = make_registered_owner(chain, operator), make_registered_owner(chain, operator)
    key_hash, public_key = _robot_key()
    added = chain.robot_key_add(owner, key_hash, public_key)

    assert not chain.has_owner_robot_keys()
    assert chain.robot_key_of_owner(key_hash, owner=owner.address) == RobotKeyOnChain(
        owner.address, added.block_number, None
    )
    assert chain.robot_key_of_owner(key_hash, owner=other.address).owner is None
    reader = ChainReader(Web3(Web3.HTTPProvider(chain.url)))
    assert reader.robot_key_of_owner(chain.address, owner.address, key_hash) == RobotKey(
        owner.address, added.block_number, None
    )
    assert reader.robot_key_of_owner(chain.address, other.address, key_hash).owner is None


def test_a_key_the_contract_would_keep_wrong_is_refused_before_sending(chain, registered_owner):
    """The contract does not hash the key; the client does, since a hash is added once."""
    key_hash, public_key = _robot_key()
    other_hash, _ = _robot_key()
    with pytest.raises(ValueError, match="64 bytes"):
        chain.robot_key_add(registered_owner, key_hash, b"\x04" + public_key)
    with pytest.raises(ValueError, match="64 bytes"):
        chain.robot_key_add(registered_owner, key_hash, public_key[:63])
    with pytest.raises(ValueError, match="not SM3"):
        chain.robot_key_add(registered_owner, other_hash, public_key)
    with pytest.raises(ValueError, match="32 bytes"):
        chain.robot_key_add(registered_owner, key_hash[:31], public_key)
    with pytest.raises(ValueError, match="32 bytes"):
        chain.robot_key_of(key_hash[:31])
    assert chain.robot_key_of(key_hash).owner is None
    assert chain.robot_key_of(other_hash).owner is None


def test_every_key_of_an_owner_is_listed_from_events(chain, operator, registered_owner):
    other = make_registered_owner(chain, operator)
    first, second, theirs = _robot_key(), _robot_key(), _robot_key()
    chain.robot_key_add(registered_owner, *first)
    chain.robot_key_add(other, *theirs)
    chain.robot_key_add(registered_owner, *second)
    chain.robot_key_revoke(registered_owner, first[0])

    mine = chain.events_naming(registered_owner.address, ROBOT_KEY_EVENTS)

    assert [(e.name, e.args["keyHash"]) for e in mine] == [
        ("RobotKeyAdded", first[0]),
        ("RobotKeyAdded", second[0]),
        ("RobotKeyRevoked", first[0]),
    ]
    assert all(e.args["owner"] == registered_owner.address for e in mine)
    # The events tell what robotKeyOf holds.
    assert chain.robot_key_of(first[0]) == RobotKeyOnChain(
        registered_owner.address, mine[0].block_number, mine[2].block_number
    )
    assert chain.robot_key_of(second[0]) == RobotKeyOnChain(
        registered_owner.address, mine[1].block_number, None
    )
    everyone = chain.events(names=["RobotKeyAdded", "RobotKeyRevoked"])
    assert [e.args["publicKey"] for e in everyone if e.name == "RobotKeyAdded"] == [
        first[1],
        theirs[1],
        second[1],
    ]
