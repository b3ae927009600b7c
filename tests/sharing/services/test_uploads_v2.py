"""Uploads of provenance v2 (DESIGN.md "Provenance v2"): a paired robot's batch signed once is
verified once and stored with each record's topic_seq; a record that does not fold to the
signed root, a swapped index, a wrong size or a reused topic_seq refuses the whole upload, with
nothing stored and a SecurityEvent; an exact resend is still a replay. Against the session's
anvil, with robots paired as the agent pairs."""

from pathlib import Path

import pytest

from sharing import errors
from sharing.models import Record, SecurityEvent
from sharing.services import uploads as uploads_module
from sharing.services.deletion import records_delete
from sharing.services.uploads import record_create_batch
from sharing.storage import envelope_storage
from smcrypto import envelope, provenance, sm2
from tests.support.batches import batch_sealed, batch_signed, seal_batch

pytestmark = pytest.mark.django_db


def _nothing_stored_since(before: set) -> bool:
    """No record and no envelope file beyond those there were `before`."""
    root = Path(envelope_storage().location)
    files = {p for p in root.rglob("*") if p.is_file()}
    return set(Record.objects.values_list("pk", flat=True)) == before and len(files) == len(before)


def test_a_v2_batch_is_verified_once_and_stored_with_its_topic_seqs(
    make_paired_robot, verifications, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    envelopes = seal_batch(setup, range(1, 51), topic_seqs=range(50))
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=setup.robot, envelopes=envelopes)
    assert sum(verifications) == 1  # fifty records, one batch, one SM2 verification
    stored = list(Record.objects.order_by("seq").values_list("seq", "topic_seq", "signer"))
    assert stored == [(seq, seq - 1, setup.robot.key_hash) for seq in range(1, 51)]
    assert [r.topic_seq for r in records] == list(range(50))
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}


def test_a_whole_batch_builds_its_tree_once_and_part_of_one_folds_each_path(
    make_paired_robot, verifications, monkeypatch
):
    """A batch whose records are all in the upload is folded once (one claim made for it);
    the records of a batch only partly in the upload each fold their own path, and hold."""
    setup = make_paired_robot("alice")
    claims_made = []
    real_claim = provenance.signature_claim

    def counting(*args):
        claims_made.append(args[1]["seq"])
        return real_claim(*args)

    monkeypatch.setattr(provenance, "signature_claim", counting)
    whole = seal_batch(setup, range(1, 31), topic_seqs=range(30))
    part = seal_batch(setup, range(31, 35), topic_seqs=range(30, 34))[:2]
    record_create_batch(robot=setup.robot, envelopes=whole + part)
    assert claims_made == [1, 31, 32]
    assert verifications == [2]  # two batches, two SM2 verifications
    assert Record.objects.count() == 32


def test_v1_from_a_paired_robot_is_still_taken_with_no_topic_seq(make_paired_robot):
    """Older agents sign each envelope (v1): accepted, and counted by no stream."""
    setup = make_paired_robot("alice")
    record_create_batch(robot=setup.robot, envelopes=[setup.seal(1), setup.seal(2)])
    assert list(Record.objects.values_list("topic_seq", flat=True)) == [None, None]
    assert set(Record.objects.values_list("signer", flat=True)) == {setup.robot.key_hash}


def test_one_record_of_a_batch_is_taken_alone(make_paired_robot):
    """The agent sends a refused batch again one by one: each record checks alone."""
    setup = make_paired_robot("alice")
    envelopes = seal_batch(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    for data in envelopes:
        record_create_batch(robot=setup.robot, envelopes=[data])
    assert sorted(Record.objects.values_list("topic_seq", flat=True)) == [0, 1, 2]


def _changed_record(setup):
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    header, _body = signed[1]
    signed[1] = (header, b'{"K": {"seq": 2, "changed": true}}')
    return batch_sealed(setup, signed)


def _swapped_index(setup):
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    signed[0][0]["sig_index"], signed[1][0]["sig_index"] = 1, 0
    return batch_sealed(setup, signed)


def _wrong_size(setup):
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    for header, _body in signed:
        header["sig_size"] = 4
    return batch_sealed(setup, signed)


def _another_batch_signature(setup):
    """A record moved in from another batch of the robot's: its place does not fold there."""
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    other = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    signed[2] = (dict(signed[2][0], sig=other[2][0]["sig"]), signed[2][1])
    return batch_sealed(setup, signed)


def _path_of_another_index(setup):
    """A record carrying another record's path: well formed, not its place in the tree."""
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    signed[1][0]["sig_path"] = signed[0][0]["sig_path"]
    return batch_sealed(setup, signed)


def _changed_topic_seq(setup):
    """topic_seq is under the signature: renumbering a record breaks its leaf."""
    signed = batch_signed(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    signed[2][0]["topic_seq"] = 7
    return batch_sealed(setup, signed)


@pytest.mark.parametrize(
    "forge",
    [
        _changed_record,
        _swapped_index,
        _wrong_size,
        _another_batch_signature,
        _path_of_another_index,
        _changed_topic_seq,
    ],
    ids=[
        "changed-record",
        "swapped-index",
        "wrong-size",
        "other-batch-sig",
        "path-of-another",
        "renumbered",
    ],
)
def test_a_batch_with_one_record_not_as_signed_is_refused_whole(make_paired_robot, forge):
    setup = make_paired_robot("alice")
    record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [0], topic_seqs=[100]))
    before = set(Record.objects.values_list("pk", flat=True))
    with pytest.raises(errors.SignatureRefused) as refused:
        record_create_batch(robot=setup.robot, envelopes=forge(setup))
    assert (refused.value.code, refused.value.http_status) == ("signature_refused", 403)
    assert _nothing_stored_since(before)
    setup.robot.refresh_from_db()
    assert setup.robot.last_seq == 0
    event = SecurityEvent.objects.get()
    assert (event.kind, event.owner_id) == (SecurityEvent.Kind.BAD_SIGNATURE, setup.owner.pk)
    assert event.detail["signer"] == setup.robot.key_hash
    assert event.detail["sig_size"] in (3, 4)


def test_a_topic_seq_stored_before_refuses_the_whole_upload(make_paired_robot):
    setup = make_paired_robot("alice")
    record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [1, 2], topic_seqs=[0, 1]))
    before = set(Record.objects.values_list("pk", flat=True))
    reused = seal_batch(setup, [3, 4], topic_seqs=[2, 1])
    with pytest.raises(errors.TopicSeqReused) as refused:
        record_create_batch(robot=setup.robot, envelopes=reused)
    assert (refused.value.code, refused.value.http_status) == ("topic_seq_reused", 409)
    assert "topic_seq 1 of /robot/odom" in str(refused.value)
    assert _nothing_stored_since(before)
    setup.robot.refresh_from_db()
    assert setup.robot.last_seq == 2  # the seq move was undone with the rest
    event = SecurityEvent.objects.get()
    assert event.kind == SecurityEvent.Kind.TOPIC_SEQ_REUSED
    assert event.owner_id == setup.owner.pk
    assert {name: event.detail[name] for name in ("topic", "topic_seq", "seq", "signer")} == {
        "topic": "/robot/odom",
        "topic_seq": 1,
        "seq": 4,
        "signer": setup.robot.key_hash,
    }
    # Another topic's count is its own: the same number there is taken.
    other_topic = seal_batch(setup, [5], topic_seqs=[1], topic="/robot/scan")
    record_create_batch(robot=setup.robot, envelopes=other_topic)
    assert Record.objects.filter(topic="/robot/scan", topic_seq=1).exists()


def test_a_deleted_records_topic_seq_is_never_used_again(
    make_paired_robot, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [1], topic_seqs=[0]))
    with django_capture_on_commit_callbacks(execute=True):  # once it is anchored
        records_delete(
            owner=setup.owner, record_ids=[Record.objects.get().pk], actor=setup.owner.user
        )
    assert Record.objects.get().is_deleted
    with pytest.raises(errors.TopicSeqReused):
        record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [2], topic_seqs=[0]))
    assert Record.objects.count() == 1
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.TOPIC_SEQ_REUSED


def test_a_topic_seq_twice_in_one_upload_refuses_it(make_paired_robot):
    setup = make_paired_robot("alice")
    twice = seal_batch(setup, [1, 2, 3], topic_seqs=[0, 1, 1])
    with pytest.raises(errors.TopicSeqReused, match="twice"):
        record_create_batch(robot=setup.robot, envelopes=twice)
    assert _nothing_stored_since(set())
    event = SecurityEvent.objects.get()
    assert (event.kind, event.detail["within_upload"]) == (
        SecurityEvent.Kind.TOPIC_SEQ_REUSED,
        True,
    )


def test_an_exact_resend_is_a_replay_not_a_reused_topic_seq(make_paired_robot):
    """Its 201 was lost: the same bytes again are answered replayed_sequence, which the agent
    counts delivered, before their topic_seqs (their own) are looked at."""
    setup = make_paired_robot("alice")
    envelopes = seal_batch(setup, [1, 2, 3], topic_seqs=[0, 1, 2])
    record_create_batch(robot=setup.robot, envelopes=envelopes)
    with pytest.raises(errors.ReplayedSequence):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    for data in envelopes:  # and one by one, as the agent sends a replayed batch again
        with pytest.raises(errors.ReplayedSequence):
            record_create_batch(robot=setup.robot, envelopes=[data])
    assert Record.objects.count() == 3
    assert not SecurityEvent.objects.exists()
    # Re-signed under the same seqs and numbers (other bytes): not a replay.
    with pytest.raises(errors.SequenceConflict):
        record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [3], topic_seqs=[2]))


def test_a_topic_seq_stored_by_an_upload_at_the_same_time_is_the_same_409(
    make_paired_robot, monkeypatch
):
    """Two uploads at once: the other one's rows committed after this one looked (its check
    saw nothing), so the database's unique constraint refuses the insert. Answered as the
    check would have answered it, never a 500."""
    setup = make_paired_robot("alice")
    record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [1], topic_seqs=[0]))
    before = set(Record.objects.values_list("pk", flat=True))
    real = uploads_module._topic_seqs_unused
    looks = []

    def looked_too_early(robot, checked):
        looks.append(len(looks))
        if len(looks) > 1:  # after the refused insert: it is there
            real(robot, checked)

    monkeypatch.setattr(uploads_module, "_topic_seqs_unused", looked_too_early)
    with pytest.raises(errors.TopicSeqReused):
        record_create_batch(robot=setup.robot, envelopes=seal_batch(setup, [2], topic_seqs=[0]))
    assert looks == [0, 1]
    assert _nothing_stored_since(before)
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.TOPIC_SEQ_REUSED


def test_a_v2_envelope_signed_by_another_key_is_refused(make_paired_robot):
    setup = make_paired_robot("alice")
    signed = batch_signed(setup, [1, 2], topic_seqs=[0, 1])
    other = sm2.generate_keypair()
    resigned = provenance.sign_batch(*other, [(h, b) for h, b in signed])
    envelopes = [envelope.seal(setup.key, h, b) for h, (_, b) in zip(resigned, signed, strict=True)]
    with pytest.raises(errors.SignatureRefused):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    assert _nothing_stored_since(set())
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.FOREIGN_SIGNER
