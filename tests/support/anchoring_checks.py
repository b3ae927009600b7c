"""What a test asserts about the chain at the end, in either anchoring mode: every record of the
database on the live chain exactly once (records mode: its id with its digest and owner; root
mode: its tree's root, anchored once by its owner's account, its proof folding to it)."""

from collections import Counter

from chainworker.client import AuthROSChain
from chainworker.codec import record_id_to_bytes32
from sharing.models import AnchorRoot, Record
from sharing.services.roots import record_path
from smcrypto.merkle import leaf_hash, root_from_path


def records_on_chain(client: AuthROSChain) -> int:
    """How many of the database's records the live chain holds: records anchored by id, and
    the records of the anchored trees whose root is on chain with its size."""
    count = client.record_count()
    for tree in AnchorRoot.objects.filter(status=AnchorRoot.Status.ANCHORED):
        on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
        if on_chain is not None and on_chain.size == tree.size:
            count += tree.size
    return count


def assert_anchored_exactly_once(client: AuthROSChain) -> None:
    records = list(Record.objects.select_related("owner", "anchor_root"))
    assert all(record.status == Record.Status.ANCHORED for record in records)
    by_id = [record for record in records if record.anchor_root_id is None]
    by_root = [record for record in records if record.anchor_root_id is not None]

    uploads = Counter(bytes(e.args["id"]) for e in client.events(names=["DataUploaded"]))
    assert set(uploads) == {record_id_to_bytes32(record.pk) for record in by_id}
    assert set(uploads.values()) <= {1}
    for record in by_id:
        on_chain = client.data_query(record.id, owner=record.owner.eoa_address)
        assert on_chain is not None, f"record {record.pk} is not on the live chain"
        assert on_chain.digest.hex() == record.digest
        assert on_chain.owner.lower() == record.owner.eoa_address.lower()

    roots = Counter(
        (e.args["sender"].lower(), bytes(e.args["root"]).hex())
        for e in client.events(names=["RootAnchored"])
    )
    assert set(roots.values()) <= {1}
    anchored = AnchorRoot.objects.filter(status=AnchorRoot.Status.ANCHORED)
    assert set(roots) == {(tree.sender.lower(), tree.root) for tree in anchored}
    assert sum(tree.size for tree in anchored) == len(by_root)  # no record in two trees
    for record in by_root:
        tree = record.anchor_root
        assert tree.status == AnchorRoot.Status.ANCHORED
        assert tree.sender.lower() == record.owner.eoa_address.lower()
        on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
        assert on_chain is not None, f"the root of record {record.pk} is not on the live chain"
        assert on_chain.size == tree.size
        leaf = leaf_hash(tree.sender, record.id, bytes.fromhex(record.digest))
        folded = root_from_path(leaf, record.leaf_index, tree.size, record_path(record))
        assert folded.hex() == tree.root
