"""A record's anchoring proof against the chain (DESIGN.md "Anchoring by Merkle roots"): the
fields of `GET /api/v1/records/{id}/proof/`, which every entry of an export's bundle holds too.

Root mode: the leaf SM3(0x00 || owner || record id || digest) folds up the path (RFC 9162
2.1.3.2) to the root, `rootOf(owner, root)` answers the tree's size and block, and the receipt
of the transaction holds the contract's RootAnchored event. Record mode:
`dataQueryOf(owner, id)` holds the owner and digest, and the receipt holds DataUploaded.
Each failure is an Invalid whose `check` is `proof` (its form), `merkle path`, `rootOf` or
`dataQuery`.
"""

import uuid
from dataclasses import dataclass
from typing import Any

from authros_verify.chain import ChainReader, Receipt
from authros_verify.values import Invalid, address, hash32, hashes32, record_id, whole
from smcrypto.merkle import leaf_hash, proof_holds

ANCHOR_FIELDS = {"chain_id", "contract", "sender", "tx", "block"}
# No receipt: a made-up transaction, or a node that keeps recent transactions only (anvil's
# --transaction-block-keeper, geth's --history.transactions) and has dropped it.
_UNKNOWN_TRANSACTION = (
    "its transaction is not known to this node (made up, or dropped by a node that keeps recent"
    " transactions only: check against a node that keeps them all)"
)


@dataclass(frozen=True)
class Anchored:
    """What a proof that holds establishes: this record of this owner, with this digest, was
    anchored on chain in this block."""

    record: uuid.UUID
    owner: str
    digest: bytes
    block: int


def anchor_check(
    proof: dict[str, Any], *, chain: ChainReader, chain_id: int, contract: str
) -> Anchored:
    """Check the proof against `contract` on the chain; Invalid naming the check if it fails."""
    try:
        return _anchor_check(proof, chain=chain, chain_id=chain_id, contract=contract)
    except Invalid as exc:
        if not exc.check:
            exc.check = "proof"
        raise
    except (KeyError, TypeError, AttributeError) as exc:
        raise Invalid(
            f"its proof is malformed ({type(exc).__name__}: {exc})", check="proof"
        ) from None


def _anchor_check(
    proof: dict[str, Any], *, chain: ChainReader, chain_id: int, contract: str
) -> Anchored:
    anchored_id = record_id(proof["record"], "record")
    owner = address(proof["owner"], "owner")
    digest = hash32(proof["digest"], "digest")
    anchor = proof["anchor"]
    if not isinstance(anchor, dict) or set(anchor) != ANCHOR_FIELDS:
        raise Invalid(f"its anchor's fields are not {sorted(ANCHOR_FIELDS)}")
    if anchor["chain_id"] != chain_id or anchor["contract"] != contract:
        raise Invalid(
            f"its anchor names chain {anchor['chain_id']} and contract {anchor['contract']}, "
            f"not chain {chain_id} and contract {contract}"
        )
    sender = address(anchor["sender"], "anchor.sender")
    hash32(anchor["tx"], "anchor.tx")
    block = whole(anchor["block"], "anchor.block")
    if sender != owner:
        raise Invalid("it was anchored by another account than its owner's")
    if proof["mode"] == "root":
        _root_check(proof, chain, contract, owner, anchored_id, digest, block)
    elif proof["mode"] == "record":
        _slot_check(proof, chain, contract, owner, anchored_id, digest, block)
    else:
        raise Invalid("its mode is neither root nor record")
    return Anchored(anchored_id, owner, digest, block)


def _root_check(
    proof: dict[str, Any],
    chain: ChainReader,
    contract: str,
    owner: str,
    anchored_id: uuid.UUID,
    digest: bytes,
    block: int,
) -> None:
    index = whole(proof["leaf_index"], "leaf_index")
    size = whole(proof["tree_size"], "tree_size")
    root = hash32(proof["root"], "root")
    path = hashes32(proof["path"], "path")
    if not proof_holds(leaf_hash(owner, anchored_id, digest), index, size, path, root):
        raise Invalid("its inclusion proof does not fold to its root", check="merkle path")
    anchored = chain.root_of(contract, owner, root)
    if anchored.size == 0:
        raise Invalid("its root is not anchored on chain by its owner", check="rootOf")
    if anchored.size != size or anchored.block != block:
        raise Invalid(
            f"the chain holds its root with size {anchored.size} in block {anchored.block}, "
            f"not size {size} in block {block}",
            check="rootOf",
        )
    receipt = _anchoring_receipt(chain, proof, block, check="rootOf")
    if receipt.root_anchored(contract, owner, root) != size:
        raise Invalid(
            "its transaction's receipt holds no RootAnchored event for its root", check="rootOf"
        )


def _anchoring_receipt(
    chain: ChainReader, proof: dict[str, Any], block: int, *, check: str
) -> Receipt:
    """The receipt of the proof's transaction, which succeeded in `block`; else Invalid."""
    receipt = chain.receipt(proof["anchor"]["tx"])
    if receipt is None:
        raise Invalid(_UNKNOWN_TRANSACTION, check=check)
    if receipt.status != 1 or receipt.block != block:
        raise Invalid("its transaction is not a successful one in its block", check=check)
    return receipt


def _slot_check(
    proof: dict[str, Any],
    chain: ChainReader,
    contract: str,
    owner: str,
    anchored_id: uuid.UUID,
    digest: bytes,
    block: int,
) -> None:
    """Record mode: dataQueryOf(owner, id) holds the digest, and the transaction uploaded it."""
    if (proof["path"], proof["leaf_index"], proof["tree_size"]) != ([], 0, 1) or proof[
        "root"
    ] != proof["digest"]:
        raise Invalid(
            "its record-mode proof is not (no path, leaf 0 of 1, root = digest)",
            check="merkle path",
        )
    slot_id = anchored_id.bytes + bytes(16)
    anchored = chain.data_query(contract, slot_id, owner=owner)
    if anchored.owner.lower() != owner.lower() or anchored.digest != digest:
        raise Invalid(
            "the chain holds another owner or digest for its id (dataQuery)", check="dataQuery"
        )
    receipt = _anchoring_receipt(chain, proof, block, check="dataQuery")
    if receipt.data_uploaded(contract, slot_id, owner) != digest:
        raise Invalid(
            "its transaction's receipt holds no DataUploaded event for it", check="dataQuery"
        )
