"""Anchoring Merkle roots (DESIGN.md "Anchoring by Merkle roots"): anchorRoot, rootOf,
RootAnchored, roots kept per sender and chained by prevRoot."""

import pytest
from eth_utils import keccak

from smcrypto.merkle import MerkleTree, leaf_hash, proof_holds

ZERO32 = b"\0" * 32
# A root: one new slot (size, time, block), the sender's last root, the event; against about
# 72,000 gas a record for dataUploadBatch.
FIRST_ROOT_GAS_CEILING = 75_000
ROOT_GAS_CEILING = 60_000


def _root(n: int) -> bytes:
    return keccak(text=f"root-{n}")


def test_a_registered_sender_anchors_a_root(w3, authros, alice, send, emitted):
    receipt = send(authros.functions.anchorRoot(_root(1), 7, ZERO32), alice)
    block = w3.eth.get_block(receipt["blockNumber"])

    assert emitted(receipt, "RootAnchored") == [
        {
            "sender": alice,
            "root": _root(1),
            "size": 7,
            "prevRoot": ZERO32,
            "time": block["timestamp"],
        }
    ]
    assert authros.functions.rootOf(alice, _root(1)).call() == [
        7,
        block["timestamp"],
        receipt["blockNumber"],
    ]
    assert authros.functions.lastRootOf(alice).call() == _root(1)


def test_a_sender_s_roots_form_one_chain(authros, alice, send, reverts):
    send(authros.functions.anchorRoot(_root(1), 1, ZERO32), alice)
    send(authros.functions.anchorRoot(_root(2), 2, _root(1)), alice)
    assert authros.functions.lastRootOf(alice).call() == _root(2)

    # A root that does not follow the last one (lost, reordered or sent twice) is refused.
    with reverts("WrongPrevRoot", _root(2), _root(1)):
        authros.functions.anchorRoot(_root(3), 1, _root(1)).transact({"from": alice})
    with reverts("WrongPrevRoot", _root(2), ZERO32):
        authros.functions.anchorRoot(_root(3), 1, ZERO32).transact({"from": alice})
    assert authros.functions.rootOf(alice, _root(3)).call()[0] == 0


def test_roots_are_kept_per_sender_so_nobody_can_squat_one(authros, alice, bob, send):
    """bob anchoring the same root first takes nothing from alice: rootOf is per sender."""
    send(authros.functions.anchorRoot(_root(1), 3, ZERO32), bob)
    send(authros.functions.anchorRoot(_root(1), 5, ZERO32), alice)
    assert authros.functions.rootOf(alice, _root(1)).call()[0] == 5
    assert authros.functions.rootOf(bob, _root(1)).call()[0] == 3
    assert authros.functions.lastRootOf(alice).call() == _root(1)


def test_the_admin_anchors_roots_without_registering(authros, admin, send):
    send(authros.functions.anchorRoot(_root(1), 9, ZERO32), admin)
    assert authros.functions.rootOf(admin, _root(1)).call()[0] == 9


def test_unknown_roots_have_size_zero(authros, alice):
    assert authros.functions.rootOf(alice, _root(1)).call() == [0, 0, 0]
    assert authros.functions.lastRootOf(alice).call() == ZERO32


def test_anchor_root_refusals(authros, alice, enrolled_only, outsider, send, reverts):
    for caller in (enrolled_only, outsider):
        with reverts("NotRegistered", caller):
            authros.functions.anchorRoot(_root(1), 1, ZERO32).transact({"from": caller})
    with reverts("EmptyRoot"):
        authros.functions.anchorRoot(ZERO32, 1, ZERO32).transact({"from": alice})
    with reverts("EmptyTree"):
        authros.functions.anchorRoot(_root(1), 0, ZERO32).transact({"from": alice})
    send(authros.functions.anchorRoot(_root(1), 1, ZERO32), alice)
    with reverts("RootExists", _root(1)):
        authros.functions.anchorRoot(_root(1), 1, _root(1)).transact({"from": alice})
    assert authros.functions.rootOf(alice, _root(1)).call()[0] == 1


@pytest.mark.parametrize("size", [1, 4096, 2**64 - 1])
def test_a_root_costs_the_same_gas_whatever_its_size(authros, alice, send, size):
    """One slot for the root, one for the sender's last root: no per-record storage."""
    first = send(authros.functions.anchorRoot(_root(1), size, ZERO32), alice)
    second = send(authros.functions.anchorRoot(_root(2), size, _root(1)), alice)
    assert first["gasUsed"] < FIRST_ROOT_GAS_CEILING  # the sender's last-root slot is new
    assert second["gasUsed"] < ROOT_GAS_CEILING
    assert authros.functions.rootOf(alice, _root(2)).call()[0] == size


def test_a_record_proof_checks_against_the_anchored_root(authros, alice, send):
    """What an outsider does with an exported proof: fold it, then ask rootOf."""
    leaves = [leaf_hash(alice, bytes([n]) * 16, keccak(text=f"envelope-{n}")) for n in range(5)]
    tree = MerkleTree(leaves)
    send(authros.functions.anchorRoot(tree.root, tree.size, ZERO32), alice)
    size, _time, _block = authros.functions.rootOf(alice, tree.root).call()
    assert size == tree.size
    assert all(proof_holds(leaves[i], i, size, tree.path(i), tree.root) for i in range(size))
