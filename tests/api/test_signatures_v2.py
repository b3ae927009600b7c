"""Provenance v2 through the REST API (DESIGN.md "Provenance v2"): a paired robot's batch
signed once is stored, verifies for its owner and a grantee, and its proof carries each
record's place in the batch and its topic_seq, enough to check the batch signature without
the portal; a batch not as signed, or a topic_seq used again, is refused whole. Against the
session's anvil."""

import base64

import pytest

from sharing.models import Record, SecurityEvent
from sharing.services.grants import grant_create
from smcrypto import envelope, provenance, sm2
from smcrypto.merkle import path_split, root_from_path
from tests.api.conftest import RECORDS, Snapshot, token_client
from tests.support.batches import batch_sealed, batch_signed, seal_batch

pytestmark = pytest.mark.django_db


def test_a_v2_batch_verifies_for_owner_and_grantee_and_its_proof_names_its_batch(
    make_paired_robot, make_owner, upload, owner_api, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    envelopes = seal_batch(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    answer = upload(token_client(setup.token), *envelopes)
    assert answer.status_code == 201, answer.content
    records = list(Record.objects.order_by("seq"))
    assert [r.topic_seq for r in records] == [0, 1, 2]
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=setup.owner, grantee=bob)
    roots = set()
    for viewer in (setup.owner, bob):
        api = owner_api(viewer)
        for index, record in enumerate(records):
            content = api.get(f"{RECORDS}{record.id}/content/")
            assert content.status_code == 200, content.content
            assert content.json()["verified"] is True
            proof = api.get(f"{RECORDS}{record.id}/proof/").json()
            assert proof["topic_seq"] == index
            batch = proof["batch"]
            assert set(batch) == {"sig_index", "sig_size", "sig_path", "root"}
            assert (batch["sig_index"], batch["sig_size"]) == (index, 3)
            # What a grantee checks without the portal: the anchored envelope opened with the
            # owner's key it was given, its leaf folded up its path to the root the robot's
            # one signature of the batch is over, that key the chain's.
            stored = base64.b64decode(proof["envelope"])
            header, plaintext = envelope.open(setup.key, stored)
            assert header["sig_path"] == batch["sig_path"]
            folded = root_from_path(
                provenance.batch_leaf(header, plaintext),
                batch["sig_index"],
                batch["sig_size"],
                path_split(bytes.fromhex(batch["sig_path"])),
            )
            assert folded.hex() == batch["root"]
            signature = proof["signature"]
            assert provenance.key_hash(signature["public_key"]) == signature["signer"]
            message = provenance.batch_message(batch["sig_size"], bytes.fromhex(batch["root"]))
            assert sm2.verify(signature["public_key"], message, signature["sig"])
            assert signature["key_owner"].lower() == setup.owner.eoa_address.lower()
            roots.add(batch["root"])
    assert len(roots) == 1  # one batch, one root


def test_a_v2_records_page_says_its_count_and_a_v1_records_does_not(
    make_paired_robot, upload, client
):
    setup = make_paired_robot("alice")
    assert (
        upload(token_client(setup.token), *seal_batch(setup, [1, 2], topic_seqs=[0, 1])).status_code
        == 201
    )
    assert upload(token_client(setup.token), setup.seal(3)).status_code == 201
    client.force_login(setup.owner.user)
    pages = {
        record.seq: client.get(f"/records/{record.id}/").content.decode()
        for record in Record.objects.all()
    }
    assert 'data-testid="record-topic-seq">#1 of <code>/robot/odom</code>' in pages[2]
    assert 'data-testid="record-topic-seq"' not in pages[3]


def test_a_v1_records_proof_is_as_before(make_paired_robot, upload, owner_api):
    setup = make_paired_robot("alice")
    assert upload(token_client(setup.token), setup.seal(1)).status_code == 201
    record = Record.objects.get()
    proof = owner_api(setup.owner).get(f"{RECORDS}{record.id}/proof/").json()
    assert "batch" not in proof
    assert "topic_seq" not in proof
    assert proof["signature"]["signer"] == setup.robot.key_hash


def test_a_v2_batch_with_a_changed_record_is_refused_whole(make_paired_robot, upload):
    setup = make_paired_robot("alice")
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    signed[2] = (signed[2][0], b'{"K": {"seq": 3, "changed": true}}')
    before = Snapshot()
    answer = upload(token_client(setup.token), *batch_sealed(setup, signed))
    assert (answer.status_code, answer.json()["error"]) == (403, "signature_refused")
    assert before.unchanged()
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.BAD_SIGNATURE


def test_a_reused_topic_seq_is_a_409_that_stores_nothing(make_paired_robot, upload):
    setup = make_paired_robot("alice")
    robot = token_client(setup.token)
    first = seal_batch(setup, [1, 2], topic_seqs=[0, 1])
    assert upload(robot, *first).status_code == 201
    before = Snapshot()
    answer = upload(robot, *seal_batch(setup, [3, 4], topic_seqs=[2, 0]))
    assert answer.status_code == 409
    body = answer.json()
    assert body["error"] == "topic_seq_reused"
    assert "topic_seq 0 of /robot/odom" in body["detail"]
    assert before.unchanged()
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.TOPIC_SEQ_REUSED
    # The exact resend of the first batch is still answered as a replay.
    again = upload(robot, *first)
    assert (again.status_code, again.json()["error"]) == (409, "replayed_sequence")
    assert SecurityEvent.objects.count() == 1
