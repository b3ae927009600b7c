"""Anchoring by Merkle roots (ANCHOR_MODE=root): trees over an owner's records, one root per
transaction chained by prevRoot, exactly once through lost and refused sends, the check at
every view folding the record's proof, and the proof answer anyone can check."""

from collections import Counter

import pytest

from accounts.selectors import owner_eoa_account
from chainworker import services as chain_services
from chainworker.errors import ChainUnavailable
from sharing.models import AnchorRoot, Grant, Record, Verdict
from sharing.services.anchoring import records_anchor
from sharing.services.grants import grant_create
from sharing.services.roots import record_path, tree_build
from sharing.services.uploads import record_create
from sharing.storage import envelope_storage
from sharing.verification.check import records_verify
from smcrypto import sm3
from smcrypto.merkle import leaf_hash, root_from_path
from tests.api.conftest import session_client, token_client
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

NO_ROOT = bytes(32)


@pytest.fixture(autouse=True)
def root_mode(settings):
    settings.ANCHOR_MODE = "root"


def _pending(setup, count: int, first: int = 1) -> list[Record]:
    return [
        record_create(robot=setup.robot, data=setup.seal(seq))
        for seq in range(first, first + count)
    ]


def _assert_anchored_once(client, owner) -> list[AnchorRoot]:
    """Every record anchored under one anchored tree of the owner, whose root the owner's
    account anchored with that size; the owner's roots chained from the first."""
    trees = list(AnchorRoot.objects.filter(owner=owner, status="anchored").order_by("created_at"))
    prev = NO_ROOT.hex()
    for tree in trees:
        assert tree.prev_root == prev
        on_chain = client.root_of(owner.eoa_address, bytes.fromhex(tree.root))
        assert on_chain is not None
        assert on_chain.size == tree.size
        prev = tree.root
    assert client.last_root_of(owner.eoa_address).hex() == prev
    for record in Record.objects.filter(owner=owner).select_related("anchor_root"):
        assert record.status == Record.Status.ANCHORED
        assert record.anchor_root.status == AnchorRoot.Status.ANCHORED
        assert record.tx_hash == record.anchor_root.tx_hash
        leaf = leaf_hash(owner.eoa_address, record.id, bytes.fromhex(record.digest))
        root = root_from_path(leaf, record.leaf_index, record.anchor_root.size, record_path(record))
        assert root.hex() == record.anchor_root.root
    leaves = sum(tree.size for tree in trees)
    assert leaves == Record.objects.filter(owner=owner).count()  # none in two trees
    return trees


def test_records_go_on_chain_under_one_root(make_robot, deployed):
    setup = make_robot()
    records = _pending(setup, 10)
    assert records_anchor(owner_id=setup.owner.pk) == 10

    (tree,) = _assert_anchored_once(deployed, setup.owner)
    assert tree.size == 10
    assert bytes(tree.leaves) == b"".join(r.id.bytes for r in records)
    assert all(
        deployed.data_query(r.id, owner=setup.owner.eoa_address) is None for r in records
    )  # no per-record storage
    assert deployed.events(names=["DataUploaded"]) == []
    (event,) = deployed.events(names=["RootAnchored"])
    assert event.args["sender"] == setup.owner.eoa_address
    assert event.tx_hash == tree.tx_hash


def test_trees_are_cut_at_their_size_and_chained(make_robot, deployed, settings):
    settings.ANCHOR_ROOT_MAX = 4
    setup = make_robot()
    _pending(setup, 10)
    assert records_anchor(owner_id=setup.owner.pk) == 10
    trees = _assert_anchored_once(deployed, setup.owner)
    assert [tree.size for tree in trees] == [4, 4, 2]


def test_records_that_come_while_a_partial_tree_is_sent_wait_for_the_next_run(
    make_robot, deployed, monkeypatch
):
    """A run sends another tree only for a backlog bigger than a tree: records uploaded while
    its last tree (not full) was sent go into one tree of their own in the next run (queued
    by this one), not a transaction each for whatever came in meanwhile."""
    from sharing.services import anchoring, roots

    setup = make_robot()
    _pending(setup, 3)
    runs = []  # per run, the sizes of the trees it sent
    run_round, send = anchoring.roots_anchor_round, roots._send

    def counted_round(*args):
        runs.append([])
        return run_round(*args)

    def send_then_more_come(client, account, tree, *, estimate):
        runs[-1].append(tree.size)
        tx_hash = send(client, account, tree, estimate=estimate)
        if runs == [[3]]:
            _pending(setup, 2, first=4)
        return tx_hash

    monkeypatch.setattr(anchoring, "roots_anchor_round", counted_round)
    monkeypatch.setattr(roots, "_send", send_then_more_come)
    assert records_anchor(owner_id=setup.owner.pk) == 3
    records_anchor(owner_id=setup.owner.pk)  # the next run, if the first did not run it yet
    assert [sizes for sizes in runs if sizes] == [[3], [2]]
    assert [tree.size for tree in _assert_anchored_once(deployed, setup.owner)] == [3, 2]


def test_a_tree_lost_before_its_send_is_sent_again_as_it_was(make_robot, deployed):
    """A run died after writing its tree: the next run sends the same root after the same
    previous root, then goes on with what came after."""
    setup = make_robot()
    lost = tree_build(
        owner=setup.owner,
        sender=setup.owner.eoa_address,
        prev_root=NO_ROOT.hex(),
        records=_pending(setup, 3),
    )
    _pending(setup, 2, first=4)
    assert records_anchor(owner_id=setup.owner.pk) == 5
    trees = _assert_anchored_once(deployed, setup.owner)
    assert trees[0].pk == lost.pk
    assert [tree.size for tree in trees] == [3, 2]


def test_a_tree_that_can_no_longer_land_gives_its_records_to_a_new_one(make_robot, deployed):
    """Another root landed after the one this tree follows (a run we lost track of): the tree
    is dropped and its records anchored once, in a new tree."""
    setup = make_robot()
    stale = tree_build(
        owner=setup.owner,
        sender=setup.owner.eoa_address,
        prev_root=NO_ROOT.hex(),
        records=_pending(setup, 3),
    )
    other = b"\x07" * 32
    deployed.anchor_root(owner_eoa_account(setup.owner), other, 1, NO_ROOT)
    assert records_anchor(owner_id=setup.owner.pk) == 3

    stale.refresh_from_db()
    assert stale.status == AnchorRoot.Status.DROPPED
    (tree,) = AnchorRoot.objects.filter(owner=setup.owner, status="anchored")
    assert tree.prev_root == other.hex()
    assert tree.root == stale.root  # the same records in the same order: the same tree
    assert deployed.last_root_of(setup.owner.eoa_address).hex() == tree.root
    assert set(Record.objects.values_list("anchor_root", flat=True)) == {tree.pk}


def test_records_put_back_to_pending_in_a_tree_on_chain_are_anchored_without_a_send(
    make_robot, deployed
):
    """An operator's re-anchor, or a run that died between two updates: the tree is on chain,
    so its records are anchored again from it; a dropped tree's records get a new tree."""
    setup = make_robot()
    _pending(setup, 3)
    assert records_anchor(owner_id=setup.owner.pk) == 3
    (tree,) = AnchorRoot.objects.all()
    Record.objects.update(status=Record.Status.PENDING)
    assert records_anchor(owner_id=setup.owner.pk) == 0
    assert set(Record.objects.values_list("status", "anchor_root")) == {("anchored", tree.pk)}
    assert len(deployed.events(names=["RootAnchored"])) == 1

    AnchorRoot.objects.update(status=AnchorRoot.Status.DROPPED)
    Record.objects.update(status=Record.Status.PENDING)
    records_anchor(owner_id=setup.owner.pk)
    assert set(Record.objects.values_list("status", flat=True)) == {"anchored"}
    assert Record.objects.exclude(anchor_root=tree).count() == 3  # in a new tree


def test_an_outage_uses_up_no_attempt(make_robot, deployed, settings, monkeypatch):
    setup = make_robot()
    _pending(setup, 3)

    def node_away(*args, **kwargs):
        raise ChainUnavailable("chain node unreachable: connection refused")

    real = deployed.anchor_root
    monkeypatch.setattr(deployed, "anchor_root", node_away)
    for _ in range(settings.ANCHOR_MAX_ATTEMPTS + 2):
        with pytest.raises(ChainUnavailable):
            records_anchor(owner_id=setup.owner.pk)
    assert set(Record.objects.values_list("status", "anchor_attempts")) == {("pending", 0)}
    monkeypatch.setattr(deployed, "anchor_root", real)
    assert records_anchor(owner_id=setup.owner.pk) == 3
    _assert_anchored_once(deployed, setup.owner)


# --- the check at every view -------------------------------------------------------------------


@pytest.fixture
def anchored(make_robot, deployed):
    setup = make_robot("alice")
    records = _pending(setup, 5)
    assert records_anchor(owner_id=setup.owner.pk) == 5
    record = Record.objects.get(pk=records[2].pk)
    return setup, record


def test_a_view_folds_the_proof_and_asks_the_chain_once(anchored, deployed, monkeypatch, settings):
    """With the chain's head and the owner's commitment seen by an earlier request, a view
    costs one eth_call (rootOf) and nothing else on chain."""
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 3600
    setup, record = anchored
    records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]  # warms head and identity
    calls = []
    real_call, real_head = deployed._read, deployed.latest_block
    monkeypatch.setattr(
        deployed, "_read", lambda name, *a: calls.append(name) or real_call(name, *a)
    )
    monkeypatch.setattr(deployed, "latest_block", lambda: calls.append("head") or real_head())
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.VERIFIED
    assert verification.verdict.chain_digest == record.digest
    assert verification.verdict.block_number >= record.block_number
    assert sm3.sm3_hex(verification.envelope) == record.digest
    assert calls == ["rootOf"]


def test_a_changed_envelope_is_tampered(anchored):
    setup, record = anchored
    tamper(record)
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.TAMPERED
    assert verification.envelope is None


@pytest.mark.parametrize(
    "change",
    [
        {"digest": "00" * 32},
        {"leaf_index": 3},
        {"merkle_path": b"\x00" * 32},
    ],
    ids=["digest", "index", "path"],
)
def test_a_changed_digest_index_or_path_in_the_database_is_tampered(anchored, change):
    """Someone with the database changes what the portal says was anchored: the proof no
    longer folds to the root on chain."""
    setup, record = anchored
    if "merkle_path" in change:
        change = {"merkle_path": change["merkle_path"] + bytes(record.merkle_path)[32:]}
    Record.objects.filter(pk=record.pk).update(**change)
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.TAMPERED


@pytest.mark.parametrize("change", [{"size": 4}, {"root": "11" * 32}], ids=["size", "root"])
def test_a_changed_tree_size_or_root_is_refused(anchored, change):
    setup, record = anchored
    AnchorRoot.objects.filter(pk=record.anchor_root_id).update(**change)
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome in (
        Verdict.Outcome.TAMPERED,
        Verdict.Outcome.NOT_ANCHORED_YET,  # a root the owner never anchored
    )
    assert verification.envelope is None


# --- the proof answer ---------------------------------------------------------------------------


def test_the_proof_checks_against_the_chain_without_the_portal(anchored, deployed):
    setup, record = anchored
    answer = session_client(setup.owner).get(f"/api/v1/records/{record.id}/proof/")
    assert answer.status_code == 200, answer.content
    proof = answer.json()
    assert proof["mode"] == "root"
    assert proof["record"] == str(record.id)
    assert proof["owner"] == setup.owner.eoa_address
    assert proof["anchor"]["chain_id"] == deployed.chain_id
    assert proof["anchor"]["contract"] == deployed.address
    assert proof["anchor"]["sender"] == setup.owner.eoa_address

    # What an outsider does: SM3 the envelope, make the leaf, fold the path, ask rootOf.
    with envelope_storage().open(record.storage_name, "rb") as handle:
        digest = sm3.sm3_digest(handle.read())
    assert "0x" + digest.hex() == proof["digest"]
    leaf = leaf_hash(proof["owner"], proof["record"], digest)
    root = root_from_path(
        leaf,
        proof["leaf_index"],
        proof["tree_size"],
        [bytes.fromhex(p.removeprefix("0x")) for p in proof["path"]],
    )
    assert "0x" + root.hex() == proof["root"]
    size, _time, block = deployed.contract.functions.rootOf(proof["anchor"]["sender"], root).call()
    assert size == proof["tree_size"]
    assert block == proof["anchor"]["block"]


def test_the_proof_is_for_the_owner_and_grantees_only(
    anchored, make_owner, django_capture_on_commit_callbacks
):
    setup, record = anchored
    grantee, stranger = make_owner("bob"), make_owner("eve")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=setup.owner, grantee=grantee)
    assert Grant.objects.get(grantee=grantee).status == Grant.Status.ACTIVE
    url = f"/api/v1/records/{record.id}/proof/"
    assert session_client(grantee).get(url).status_code == 200
    refused = session_client(stranger).get(url)
    assert refused.status_code == 404
    assert refused.json()["error"] == "not_found"
    assert token_client(setup.token).get(url).status_code == 403  # the robot's token
    assert session_client(setup.owner).get("/api/v1/records/not-a-uuid/proof/").status_code == 404


def test_no_proof_while_pending(make_robot, deployed):
    setup = make_robot()
    (record,) = _pending(setup, 1)
    answer = session_client(setup.owner).get(f"/api/v1/records/{record.id}/proof/")
    assert answer.status_code == 409
    assert answer.json()["error"] == "not_anchored_yet"


# --- reconciliation -----------------------------------------------------------------------------


def _root_events(client) -> Counter:
    return Counter(bytes(e.args["root"]).hex() for e in client.events(names=["RootAnchored"]))


def test_roots_the_chain_lost_are_sent_again_as_they_were(
    make_robot, deployed, settings, reconcile, blocks_lost
):
    """The node lost the blocks with the last two of three roots: the reconciliation sends
    the same roots again, after the same previous roots, and every record verifies."""
    settings.ANCHOR_ROOT_MAX = 3
    setup = make_robot()
    _pending(setup, 3)
    assert records_anchor(owner_id=setup.owner.pk) == 3
    with blocks_lost():
        _pending(setup, 6, first=4)
        assert records_anchor(owner_id=setup.owner.pk) == 6
        trees = _assert_anchored_once(deployed, setup.owner)

    counts = reconcile()

    assert counts["roots_lost"] == 2
    assert _assert_anchored_once(deployed, setup.owner) == trees  # the same trees
    assert set(_root_events(deployed).values()) == {1}
    for record in Record.objects.all():
        verdict = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict
        assert verdict.outcome == Verdict.Outcome.VERIFIED
    assert reconcile()["roots_lost"] == 0


def test_a_reset_chain_gets_every_root_again(
    make_robot, deployed, settings, fresh_chain, reconcile
):
    settings.ANCHOR_ROOT_MAX = 2
    setup = make_robot()
    _pending(setup, 5)
    assert records_anchor(owner_id=setup.owner.pk) == 5
    trees = _assert_anchored_once(deployed, setup.owner)
    fresh_chain()

    counts = reconcile()

    assert counts["identity"] == "reset"
    assert counts["roots"] == 3
    client = chain_services.chain_client()
    assert _assert_anchored_once(client, setup.owner) == trees
    record = Record.objects.first()
    verdict = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict
    assert verdict.outcome == Verdict.Outcome.VERIFIED
