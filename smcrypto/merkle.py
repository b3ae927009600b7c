"""Merkle trees of records (DESIGN.md "Anchoring by Merkle roots"): the shape of RFC 9162
section 2.1 with SM3 in place of SHA-256. Pure functions, no Django, no chain: anyone holding
a record's envelope and its proof can fold the proof to the root without the portal.

    leaf  = leaf_hash(owner_eoa, record_id, sm3(envelope))
    tree  = MerkleTree([leaf, ...])            # tree.root, tree.path(index)
    root  = root_from_path(leaf, index, size, path)   # RFC 9162 2.1.3.2; InvalidProof if not
"""

from __future__ import annotations

import functools
import uuid
from collections.abc import Sequence

from smcrypto.sm3 import DIGEST_SIZE, sm3_digest

LEAF_PREFIX = b"\x00"
NODE_PREFIX = b"\x01"
ADDRESS_SIZE = 20
RECORD_ID_SIZE = 16


class InvalidProof(ValueError):
    """The inclusion proof does not fold to a root (bad index, size or path)."""


def leaf_hash(owner: str | bytes, record_id: uuid.UUID | str | bytes, digest: bytes | str) -> bytes:
    """SM3(0x00 || owner EOA (20 bytes) || record id (16 bytes of the UUID) || digest (32))."""
    owner_bytes = _fixed(owner, ADDRESS_SIZE, "owner address")
    if isinstance(record_id, uuid.UUID):
        id_bytes = record_id.bytes
    elif isinstance(record_id, str):
        id_bytes = uuid.UUID(record_id).bytes
    else:
        id_bytes = _fixed(record_id, RECORD_ID_SIZE, "record id")
    digest_bytes = _fixed(digest, DIGEST_SIZE, "digest")
    return sm3_digest(LEAF_PREFIX + owner_bytes + id_bytes + digest_bytes)


def node_hash(left: bytes, right: bytes) -> bytes:
    """SM3(0x01 || left || right)."""
    return _node_hash(bytes(left), bytes(right))


# A pure function: the records of one tree checked together fold the same upper nodes, so each
# node is hashed once for them all (about a tree's size in all, not size * log2(size)). Enough
# for the trees of one check's slice; about 5 MB at most.
@functools.lru_cache(maxsize=1 << 14)
def _node_hash(left: bytes, right: bytes) -> bytes:
    return sm3_digest(NODE_PREFIX + left + right)


def _split(size: int) -> int:
    """The largest power of two smaller than size (size >= 2)."""
    return 1 << ((size - 1).bit_length() - 1)


class MerkleTree:
    """The tree over `leaves` (leaf hashes, in order): its root and every leaf's audit path,
    computed once (n - 1 node hashes, paths of at most log2(n) + 1 hashes)."""

    def __init__(self, leaves: Sequence[bytes]) -> None:
        if not leaves:
            raise ValueError("a Merkle tree needs at least one leaf")
        self.leaves = list(leaves)
        self._paths: list[list[bytes]] = [[] for _ in self.leaves]
        self.root = self._build(0, len(self.leaves))

    @property
    def size(self) -> int:
        return len(self.leaves)

    def path(self, index: int) -> list[bytes]:
        """The audit path of leaf `index`, bottom up (RFC 9162 2.1.3.1)."""
        if not 0 <= index < self.size:
            raise IndexError(f"leaf {index} is outside a tree of {self.size}")
        return list(self._paths[index])

    def _build(self, low: int, high: int) -> bytes:
        if high - low == 1:
            return self.leaves[low]
        middle = low + _split(high - low)
        left = self._build(low, middle)
        right = self._build(middle, high)
        # Deeper levels were appended by the calls above: paths run from the leaf up.
        for index in range(low, middle):
            self._paths[index].append(right)
        for index in range(middle, high):
            self._paths[index].append(left)
        return node_hash(left, right)


def root_from_path(leaf: bytes, index: int, size: int, path: Sequence[bytes]) -> bytes:
    """The root that `path` proves leaf `index` of a tree of `size` leaves belongs to,
    folded as RFC 9162 section 2.1.3.2 says; InvalidProof if the proof cannot hold."""
    if size < 1 or not 0 <= index < size:
        raise InvalidProof(f"leaf index {index} is outside a tree of {size}")
    if len(leaf) != DIGEST_SIZE:
        raise InvalidProof(f"every hash is {DIGEST_SIZE} bytes")
    # The memoised node hash is called directly (no wrapper per level): a check folds two
    # paths a record, each a level per doubling of its tree.
    fn, sn, result = index, size - 1, bytes(leaf)
    for sibling in path:
        if len(sibling) != DIGEST_SIZE:
            raise InvalidProof(f"every hash is {DIGEST_SIZE} bytes")
        if sn == 0:
            raise InvalidProof("the path is longer than the tree is deep")
        if fn & 1 or fn == sn:
            result = _node_hash(bytes(sibling), result)
            while not fn & 1 and fn != 0:
                fn >>= 1
                sn >>= 1
        else:
            result = _node_hash(result, bytes(sibling))
        fn >>= 1
        sn >>= 1
    if sn != 0:
        raise InvalidProof("the path is shorter than the tree is deep")
    return result


def proof_holds(leaf: bytes, index: int, size: int, path: Sequence[bytes], root: bytes) -> bool:
    """Whether `path` proves leaf `index` of a tree of `size` leaves under `root`."""
    try:
        return root_from_path(leaf, index, size, path) == root
    except InvalidProof:
        return False


def path_split(raw: bytes) -> list[bytes]:
    """An audit path stored as its hashes one after the other (b"".join(path)), as a list."""
    raw = bytes(raw)
    return [raw[i : i + DIGEST_SIZE] for i in range(0, len(raw), DIGEST_SIZE)]


def _fixed(value: str | bytes, size: int, what: str) -> bytes:
    raw = bytes.fromhex(value.removeprefix("0x")) if isinstance(value, str) else bytes(value)
    if len(raw) != size:
        raise ValueError(f"{what} must be {size} bytes, not {len(raw)}")
    return raw
