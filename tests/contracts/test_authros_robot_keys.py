"""Robot signing keys on chain (DESIGN.md "Provenance: robots sign what they capture"):
robotKeyAdd, robotKeyRevoke, robotKeyOfOwner (keys kept per owner, issue 46), robotKeyOf (the
first owner, for old readers), their events and every refusal."""

import pytest
from eth_utils import event_abi_to_log_topic

from smcrypto import sm2, sm3

ZERO32 = b"\0" * 32
ZERO_ADDRESS = "0x" + "00" * 20
PUBLIC_KEY_LENGTH = 64
# Adding: two new slots (the owner's entry; the first owner and addedBlock) and an event
# carrying the 64-byte key (about 74,000); revoking: the owner's entry and the first owner's
# revokedBlock, a new slot, and an event (about 54,000).
ADD_GAS_CEILING = 80_000
REVOKE_GAS_CEILING = 60_000


def robot_key(n: int) -> tuple[bytes, bytes]:
    """(keyHash, publicKey) of the n-th test robot: a real SM2 key `x||y` and its SM3."""
    public_key = bytes.fromhex(sm2.public_key_from_private(f"{n + 1:064x}"))[1:]
    return sm3.sm3_digest(public_key), public_key


KEY_1, KEY_2, KEY_3 = robot_key(1), robot_key(2), robot_key(3)


def test_an_owner_adds_a_robot_key(authros, alice, send, emitted):
    key_hash, public_key = KEY_1
    assert authros.functions.robotKeyOf(key_hash).call() == [ZERO_ADDRESS, 0, 0]

    receipt = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)

    assert emitted(receipt, "RobotKeyAdded") == [
        {"owner": alice, "keyHash": key_hash, "publicKey": public_key}
    ]
    assert authros.functions.robotKeyOf(key_hash).call() == [alice, receipt["blockNumber"], 0]
    assert receipt["gasUsed"] < ADD_GAS_CEILING


def test_the_owner_revokes_its_robot_key(w3, authros, alice, send, emitted):
    key_hash, public_key = KEY_1
    added = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)
    w3.provider.make_request("evm_mine", [])  # revocation in a later block than the addition

    receipt = send(authros.functions.robotKeyRevoke(key_hash), alice)

    assert emitted(receipt, "RobotKeyRevoked") == [{"owner": alice, "keyHash": key_hash}]
    assert receipt["blockNumber"] > added["blockNumber"] + 1
    assert authros.functions.robotKeyOf(key_hash).call() == [
        alice,
        added["blockNumber"],
        receipt["blockNumber"],
    ]
    assert receipt["gasUsed"] < REVOKE_GAS_CEILING


def test_keys_are_kept_apart_by_hash_and_owner(authros, alice, bob, send):
    send(authros.functions.robotKeyAdd(*KEY_1), alice)
    send(authros.functions.robotKeyAdd(*KEY_2), alice)
    send(authros.functions.robotKeyAdd(*KEY_3), bob)
    send(authros.functions.robotKeyRevoke(KEY_2[0]), alice)

    owners = [authros.functions.robotKeyOf(key[0]).call()[0] for key in (KEY_1, KEY_2, KEY_3)]
    revoked = [authros.functions.robotKeyOf(key[0]).call()[2] for key in (KEY_1, KEY_2, KEY_3)]
    assert owners == [alice, alice, bob]
    assert [block != 0 for block in revoked] == [False, True, False]


def test_events_index_the_owner_and_the_key_hash(authros, alice, send):
    key_hash, public_key = KEY_1
    added = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)
    revoked = send(authros.functions.robotKeyRevoke(key_hash), alice)
    owner_topic = bytes.fromhex(alice[2:]).rjust(32, b"\0")

    for receipt, name in ((added, "RobotKeyAdded"), (revoked, "RobotKeyRevoked")):
        (log,) = receipt["logs"]
        signature = event_abi_to_log_topic(authros.events[name].abi)
        assert [bytes(topic) for topic in log["topics"]] == [signature, owner_topic, key_hash]
    # The key itself is in the data (not indexed), so a log names it in full.
    assert authros.events.RobotKeyAdded().process_log(added["logs"][0])["args"]["publicKey"] == (
        public_key
    )


def test_every_key_of_an_owner_is_listed_from_events_alone(w3, authros, alice, bob, send):
    """What `authros_verify keys` does: one log query by owner topic, no contract state, and
    each key checked against its hash."""
    blocks = {}
    for key in (KEY_1, KEY_2):
        blocks[key[0]] = [send(authros.functions.robotKeyAdd(*key), alice)["blockNumber"], 0]
    send(authros.functions.robotKeyAdd(*KEY_3), bob)
    blocks[KEY_1[0]][1] = send(authros.functions.robotKeyRevoke(KEY_1[0]), alice)["blockNumber"]
    send(authros.functions.robotKeyRevoke(KEY_3[0]), bob)

    added, revoked = (authros.events[name]() for name in ("RobotKeyAdded", "RobotKeyRevoked"))
    signatures = ["0x" + event_abi_to_log_topic(event.abi).hex() for event in (added, revoked)]
    owner_topic = "0x" + alice[2:].lower().rjust(64, "0")
    logs = w3.eth.get_logs(
        {
            "address": authros.address,
            "fromBlock": 0,
            "toBlock": "latest",
            "topics": [signatures, owner_topic],
        }
    )

    listed = {}
    for log in logs:
        if bytes(log["topics"][0]).hex() == signatures[0][2:]:
            args = added.process_log(log)["args"]
            assert sm3.sm3_digest(args["publicKey"]) == args["keyHash"]
            listed[args["keyHash"]] = [args["publicKey"], log["blockNumber"], 0]
        else:
            listed[revoked.process_log(log)["args"]["keyHash"]][2] = log["blockNumber"]
    assert listed == {
        KEY_1[0]: [KEY_1[1], *blocks[KEY_1[0]]],
        KEY_2[0]: [KEY_2[1], *blocks[KEY_2[0]]],
    }
    # The events and the contract's state tell the same story.
    for key_hash, (_public_key, added_block, revoked_block) in listed.items():
        assert authros.functions.robotKeyOf(key_hash).call() == [alice, added_block, revoked_block]


def test_add_refuses_an_unregistered_caller(authros, enrolled_only, outsider, reverts):
    for caller in (enrolled_only, outsider):
        with reverts("NotRegistered", caller):
            authros.functions.robotKeyAdd(*KEY_1).transact({"from": caller})
    assert authros.functions.robotKeyOf(KEY_1[0]).call() == [ZERO_ADDRESS, 0, 0]


def test_add_refuses_a_zero_key_hash(authros, alice, reverts):
    with reverts("EmptyKeyHash"):
        authros.functions.robotKeyAdd(ZERO32, KEY_1[1]).transact({"from": alice})
    assert authros.functions.robotKeyOf(ZERO32).call() == [ZERO_ADDRESS, 0, 0]


@pytest.mark.parametrize("length", [0, 63, 65])
def test_add_refuses_a_public_key_that_is_not_x_y(authros, alice, reverts, length):
    key_hash, public_key = KEY_1
    wrong = (b"\x04" + public_key)[:length]  # 65: the 04||x||y form is refused too
    with reverts("WrongPublicKeyLength", length, PUBLIC_KEY_LENGTH):
        authros.functions.robotKeyAdd(key_hash, wrong).transact({"from": alice})
    assert authros.functions.robotKeyOf(key_hash).call() == [ZERO_ADDRESS, 0, 0]


def test_add_refuses_a_key_hash_the_owner_added_even_once_revoked(authros, alice, send, reverts):
    key_hash, public_key = KEY_1
    added = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)
    with reverts("RobotKeyExists", key_hash):
        authros.functions.robotKeyAdd(key_hash, public_key).transact({"from": alice})
    # The same hash with another key is still the same hash: taken.
    with reverts("RobotKeyExists", key_hash):
        authros.functions.robotKeyAdd(key_hash, KEY_2[1]).transact({"from": alice})

    revoked = send(authros.functions.robotKeyRevoke(key_hash), alice)

    # A revoked key never comes back for its owner.
    with reverts("RobotKeyExists", key_hash):
        authros.functions.robotKeyAdd(key_hash, public_key).transact({"from": alice})
    blocks = [added["blockNumber"], revoked["blockNumber"]]
    assert authros.functions.robotKeyOfOwner(alice, key_hash).call() == blocks
    assert authros.functions.robotKeyOf(key_hash).call() == [alice, *blocks]


def test_another_owner_s_registration_neither_blocks_nor_replaces_a_key(
    authros, alice, bob, send, emitted
):
    """Issue 46: bob names alice's robot's key (any grantee reads it in a proof answer). Before
    alice: her own registration still goes through; after: hers stays as it was. Each owner's
    entry is its own; robotKeyOf keeps the first owner, whoever that was."""
    key_hash, public_key = KEY_1
    squat = send(authros.functions.robotKeyAdd(key_hash, public_key), bob)

    added = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)

    assert emitted(added, "RobotKeyAdded") == [
        {"owner": alice, "keyHash": key_hash, "publicKey": public_key}
    ]
    assert authros.functions.robotKeyOfOwner(alice, key_hash).call() == [added["blockNumber"], 0]
    assert authros.functions.robotKeyOfOwner(bob, key_hash).call() == [squat["blockNumber"], 0]
    assert authros.functions.robotKeyOf(key_hash).call() == [bob, squat["blockNumber"], 0]

    # Each revokes its own entry only; the first owner's revocation shows in robotKeyOf.
    revoked = send(authros.functions.robotKeyRevoke(key_hash), alice)
    assert authros.functions.robotKeyOfOwner(alice, key_hash).call() == [
        added["blockNumber"],
        revoked["blockNumber"],
    ]
    assert authros.functions.robotKeyOfOwner(bob, key_hash).call() == [squat["blockNumber"], 0]
    assert authros.functions.robotKeyOf(key_hash).call() == [bob, squat["blockNumber"], 0]
    gone = send(authros.functions.robotKeyRevoke(key_hash), bob)
    assert authros.functions.robotKeyOf(key_hash).call() == [
        bob,
        squat["blockNumber"],
        gone["blockNumber"],
    ]


def test_robot_key_of_owner_is_zero_for_an_owner_that_never_added_it(authros, alice, bob, send):
    send(authros.functions.robotKeyAdd(*KEY_1), alice)
    assert authros.functions.robotKeyOfOwner(bob, KEY_1[0]).call() == [0, 0]
    assert authros.functions.robotKeyOfOwner(alice, KEY_2[0]).call() == [0, 0]


def test_revoke_refuses_an_unknown_key(authros, alice, outsider, reverts):
    for caller in (alice, outsider):
        with reverts("RobotKeyUnknown", KEY_1[0]):
            authros.functions.robotKeyRevoke(KEY_1[0]).transact({"from": caller})
    with reverts("RobotKeyUnknown", ZERO32):
        authros.functions.robotKeyRevoke(ZERO32).transact({"from": alice})


def test_revoke_refuses_an_eoa_that_did_not_add_the_key(
    authros, alice, bob, admin, outsider, send, reverts
):
    key_hash, public_key = KEY_1
    added = send(authros.functions.robotKeyAdd(key_hash, public_key), alice)
    for caller in (bob, admin, outsider):
        with reverts("RobotKeyUnknown", key_hash):
            authros.functions.robotKeyRevoke(key_hash).transact({"from": caller})
    assert authros.functions.robotKeyOf(key_hash).call() == [alice, added["blockNumber"], 0]
    assert authros.functions.robotKeyOfOwner(alice, key_hash).call() == [added["blockNumber"], 0]


def test_revoke_refuses_twice(authros, alice, bob, send, reverts):
    key_hash, public_key = KEY_1
    send(authros.functions.robotKeyAdd(key_hash, public_key), alice)
    revoked = send(authros.functions.robotKeyRevoke(key_hash), alice)
    with reverts("RobotKeyAlreadyRevoked", key_hash):
        authros.functions.robotKeyRevoke(key_hash).transact({"from": alice})
    with reverts("RobotKeyUnknown", key_hash):
        authros.functions.robotKeyRevoke(key_hash).transact({"from": bob})
    assert authros.functions.robotKeyOf(key_hash).call()[2] == revoked["blockNumber"]


def test_robot_keys_survive_the_owner_s_key_rotation(authros, alice, send):
    """A robot key is bound to the EOA, not to the SM4 key commitment."""
    added = send(authros.functions.robotKeyAdd(*KEY_1), alice)
    send(authros.functions.rotateKey(b"\x01" * 32), alice)
    assert authros.functions.robotKeyOf(KEY_1[0]).call() == [alice, added["blockNumber"], 0]
    send(authros.functions.robotKeyRevoke(KEY_1[0]), alice)
