"""The record trees of DESIGN.md "Anchoring by Merkle roots" against an independent reference:
RFC 9162 section 2.1 written out as the RFC states it, over gmssl's pure-Python SM3."""

import random
import uuid

import pytest
from gmssl import func
from gmssl.sm3 import sm3_hash

from smcrypto.merkle import (
    InvalidProof,
    MerkleTree,
    leaf_hash,
    node_hash,
    proof_holds,
    root_from_path,
)


def _sm3(data: bytes) -> bytes:
    return bytes.fromhex(sm3_hash(func.bytes_to_list(data)))


def _mth(leaves: list[bytes]) -> bytes:
    """MTH(D[n]) of RFC 9162 2.1.1, leaves already hashed."""
    if len(leaves) == 1:
        return leaves[0]
    k = 1
    while k * 2 < len(leaves):
        k *= 2
    return _sm3(b"\x01" + _mth(leaves[:k]) + _mth(leaves[k:]))


def _rfc_path(m: int, leaves: list[bytes]) -> list[bytes]:
    """PATH(m, D[n]) of RFC 9162 2.1.3.1."""
    if len(leaves) == 1:
        return []
    k = 1
    while k * 2 < len(leaves):
        k *= 2
    if m < k:
        return [*_rfc_path(m, leaves[:k]), _mth(leaves[k:])]
    return [*_rfc_path(m - k, leaves[k:]), _mth(leaves[:k])]


def _leaves(count: int, seed: int = 7) -> list[bytes]:
    rng = random.Random(seed)
    return [rng.randbytes(32) for _ in range(count)]


def test_the_leaf_binds_owner_record_and_digest_as_designed():
    owner = "0x" + "ab" * 20
    record = uuid.UUID("12345678-9abc-def0-1234-56789abcdef0")
    digest = bytes(range(32))
    expected = _sm3(b"\x00" + bytes.fromhex("ab" * 20) + record.bytes + digest)
    assert leaf_hash(owner, record, digest) == expected
    assert leaf_hash(bytes.fromhex("ab" * 20), str(record), digest.hex()) == expected
    assert node_hash(b"\x01" * 32, b"\x02" * 32) == _sm3(b"\x01" + b"\x01" * 32 + b"\x02" * 32)
    assert leaf_hash(owner, record, b"\x00" * 32) != expected
    assert leaf_hash("0x" + "ac" * 20, record, digest) != expected


@pytest.mark.parametrize("value", ["0x1234", b"\x00" * 19, b"\x00" * 21])
def test_a_leaf_refuses_an_owner_of_the_wrong_size(value):
    with pytest.raises(ValueError, match="owner address"):
        leaf_hash(value, uuid.uuid4(), b"\x00" * 32)


@pytest.mark.parametrize("size", [*range(1, 34), 63, 64, 65, 100])
def test_root_and_every_path_match_the_rfc(size):
    leaves = _leaves(size)
    tree = MerkleTree(leaves)
    assert tree.root == _mth(leaves)
    for index in range(size):
        path = tree.path(index)
        assert path == _rfc_path(index, leaves)
        assert root_from_path(leaves[index], index, size, path) == tree.root


@pytest.mark.parametrize("size", [1, 2, 3, 1023, 1024, 1025, 4095, 4096])
def test_every_proof_folds_up_to_4096_leaves(size):
    leaves = _leaves(size, seed=size)
    tree = MerkleTree(leaves)
    assert all(proof_holds(leaves[i], i, size, tree.path(i), tree.root) for i in range(size))
    if size <= 1025:  # the pure-Python reference is slow
        assert tree.root == _mth(leaves)


def test_a_changed_digest_path_index_size_or_root_is_refused():
    leaves = _leaves(13)
    tree = MerkleTree(leaves)
    leaf, index, path, root = leaves[6], 6, tree.path(6), tree.root
    assert proof_holds(leaf, index, 13, path, root)

    assert not proof_holds(leaves[7], index, 13, path, root)  # another record
    assert not proof_holds(b"\x00" * 32, index, 13, path, root)
    for position in range(len(path)):
        changed = list(path)
        changed[position] = bytes([path[position][0] ^ 1]) + path[position][1:]
        assert not proof_holds(leaf, index, 13, changed, root)
    assert not proof_holds(leaf, index, 13, path[:-1], root)  # shorter
    assert not proof_holds(leaf, index, 13, [*path, path[0]], root)  # longer
    assert not proof_holds(leaf, index, 13, list(reversed(path)), root)
    for other in (5, 7, 12, 13, -1, 100):
        assert not proof_holds(leaf, other, 13, path, root)
    # A size of another shape folds differently. (Sizes of the same shape, 9 to 16 here, fold
    # alike: RFC 9162 roots do not bind the size, so a check compares it with rootOf's.)
    for other in (0, 1, 6, 7, 8, 17, 32, 1 << 40):
        assert not proof_holds(leaf, index, other, path, root)
    assert not proof_holds(leaf, index, 13, path, bytes(32))


@pytest.mark.parametrize(
    ("index", "size", "path"),
    [(0, 0, []), (3, 3, []), (-1, 4, []), (0, 2, [b"\x00" * 31]), (0, 1, [b"\x00" * 32])],
)
def test_a_proof_that_cannot_hold_is_invalid(index, size, path):
    with pytest.raises(InvalidProof):
        root_from_path(b"\x00" * 32, index, size, path)


def test_a_tree_needs_a_leaf_and_paths_stay_inside_it():
    with pytest.raises(ValueError, match="at least one leaf"):
        MerkleTree([])
    tree = MerkleTree(_leaves(3))
    with pytest.raises(IndexError):
        tree.path(3)
    assert tree.size == 3
    assert MerkleTree(_leaves(1)).path(0) == []
