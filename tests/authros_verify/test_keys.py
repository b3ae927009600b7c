"""`authros_verify keys`: every robot key ever registered for an owner, from chain events alone,
matches what was paired, registered and revoked; a key the owner never paired (registered from
its EOA by whoever holds the portal's KEK) is listed too, which is the point."""

import json

import pytest

from accounts.selectors import owner_eoa_account
from authros_verify import ChainReader, robot_keys
from authros_verify.__main__ import main
from smcrypto import provenance, sm2

pytestmark = pytest.mark.django_db


def _xy(public_key: str) -> bytes:
    return bytes.fromhex(sm2.public_key_normalize(public_key))[1:]


def test_every_key_of_an_owner_is_listed_with_its_blocks(
    make_paired_robot, deployed, isolated_portal, capsys
):
    alice, bob = make_paired_robot("alice"), make_paired_robot("bob")
    account = owner_eoa_account(alice.owner)
    paired = bytes.fromhex(alice.robot.key_hash)
    # A key alice never paired, registered from her EOA (what the KEK's holder could do), and
    # later revoked; the key of her paired robot stays live. bob's key is not hers.
    unpaired = sm2.generate_keypair()[1]
    unpaired_hash = bytes.fromhex(provenance.key_hash(unpaired))
    added = deployed.robot_key_add(account, unpaired_hash, _xy(unpaired))
    revoked = deployed.robot_key_revoke(account, unpaired_hash)

    keys = robot_keys(ChainReader(deployed.w3), contract=deployed.address, owner=account.address)
    listed = {
        key.key_hash: (key.public_key, key.added_block, key.revoked_block, key.hash_holds)
        for key in keys
    }
    assert listed == {
        paired: (
            _xy(alice.signing_key[1]),
            deployed.robot_key_of(paired).added_block,
            None,
            True,
        ),
        unpaired_hash: (_xy(unpaired), added.block_number, revoked.block_number, True),
    }
    assert [key.key_hash for key in keys] == [paired, unpaired_hash]  # in the order added
    # The events and the contract's state tell the same story.
    for key in keys:
        on_chain = deployed.robot_key_of(key.key_hash)
        assert (on_chain.owner, on_chain.added_block, on_chain.revoked_block) == (
            account.address,
            key.added_block,
            key.revoked_block,
        )

    arguments = ["keys", "--owner", account.address.lower(), "--rpc", isolated_portal]
    assert main([*arguments, "--contract", deployed.address]) == 0
    out = capsys.readouterr().out
    assert f"key 0x{paired.hex()}  added in block" in out
    assert f"revoked in block {revoked.block_number}" in out
    assert sm2.fingerprint(alice.signing_key[1]) in out
    assert "2 robot keys, 1 live" in out
    assert bob.robot.key_hash not in out
    assert main([*arguments, "--contract", deployed.address, "--json"]) == 0
    as_json = json.loads(capsys.readouterr().out)
    assert [(key["key_hash"], key["revoked_block"]) for key in as_json] == [
        ("0x" + paired.hex(), None),
        ("0x" + unpaired_hash.hex(), revoked.block_number),
    ]
    # No contract there, no node there: nothing could be listed.
    assert main([*arguments, "--contract", "0x" + "11" * 20]) == 2
    unreachable = ["keys", "--owner", account.address, "--rpc", "http://127.0.0.1:9"]
    assert main([*unreachable, "--contract", deployed.address]) == 2


def test_a_key_whose_public_key_does_not_hash_to_it_is_flagged(
    make_owner, deployed, isolated_portal, capsys
):
    """The contract cannot afford SM3: a key sent to it directly (not through the portal's
    client, which refuses a mismatch) may not hash to its keyHash."""
    owner = make_owner("dave")
    account = owner_eoa_account(owner)
    public_key = _xy(sm2.generate_keypair()[1])
    wrong_hash = bytes.fromhex(provenance.key_hash(sm2.generate_keypair()[1]))
    call = deployed.contract.functions.robotKeyAdd(wrong_hash, public_key)
    transaction = call.build_transaction(
        {"from": account.address, "nonce": deployed.w3.eth.get_transaction_count(account.address)}
    )
    signed = account.sign_transaction(transaction)
    receipt = deployed.w3.eth.wait_for_transaction_receipt(
        deployed.w3.eth.send_raw_transaction(signed.raw_transaction)
    )
    assert receipt["status"] == 1

    (key,) = robot_keys(ChainReader(deployed.w3), contract=deployed.address, owner=account.address)
    assert (key.key_hash, key.hash_holds) == (wrong_hash, False)
    arguments = ["keys", "--owner", account.address, "--rpc", isolated_portal]
    assert main([*arguments, "--contract", deployed.address]) == 1
    assert "MISMATCH" in capsys.readouterr().out
