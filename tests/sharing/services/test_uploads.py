"""Uploading records: what is stored and anchored, and what is refused without a trace."""

from datetime import timedelta
from pathlib import Path

import pytest
from django.db import DatabaseError
from django.utils import timezone

from accounts.services.keys import key_rotate
from core import files as files_module
from sharing import errors
from sharing import storage as storage_module
from sharing.cache import envelope_cache_get
from sharing.models import Record, SecurityEvent
from sharing.services import uploads as uploads_module
from sharing.services.uploads import record_create, record_create_batch
from sharing.storage import envelope_storage
from smcrypto import envelope, sm3, sm4
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db


def _nothing_stored() -> bool:
    """No record and no envelope file (an empty folder is not data)."""
    root = Path(envelope_storage().location)
    return Record.objects.count() == 0 and not any(p.is_file() for p in root.rglob("*"))


@pytest.mark.usefixtures("records_mode")
def test_upload_is_stored_cached_and_anchored(
    make_robot, deployed, django_capture_on_commit_callbacks
):
    setup = make_robot()
    data = setup.seal(1, plaintext=b'{"K": 1}')
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create(robot=setup.robot, data=data)
    record.refresh_from_db()
    assert record.digest == sm3.sm3_hex(data)
    assert record.size == len(data)
    assert record.seq == 1
    assert record.topic == "/robot/odom"
    assert record.data_type == "nav_msgs/Odometry"
    with envelope_storage().open(record.storage_name, "rb") as handle:
        assert handle.read() == data
    assert envelope_cache_get(record.id) == data
    assert record.status == Record.Status.ANCHORED
    assert record.tx_hash.startswith("0x")
    assert record.block_number > 0
    on_chain = deployed.data_query(record.id, owner=record.owner.eoa_address)
    assert on_chain.digest.hex() == record.digest
    assert on_chain.owner == setup.owner.eoa_address
    assert on_chain.time == record.captured_at
    setup.robot.refresh_from_db()
    assert setup.robot.last_seq == 1


@pytest.mark.usefixtures("records_mode")
def test_batch_goes_in_one_transaction(make_robot, deployed, django_capture_on_commit_callbacks):
    setup = make_robot()
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(
            robot=setup.robot, envelopes=[setup.seal(seq) for seq in range(1, 11)]
        )
    tx_hashes = set(Record.objects.values_list("tx_hash", flat=True))
    assert len(records) == 10
    assert len(tx_hashes) == 1
    assert len(deployed.events(names=["DataUploaded"])) == 10


def test_bad_uploads_are_refused_and_change_nothing(make_robot):
    setup = make_robot()
    other = make_robot()
    good = setup.seal(5)
    tampered = bytearray(good)
    tampered[-1] ^= 0x01
    key_id_forged = bytearray(
        other.seal(5, owner=setup.owner.username, robot_id=str(setup.robot.id))
    )
    key_id_forged[4:12] = envelope.key_id(setup.key)
    cases = [
        (b"not an envelope", errors.InvalidEnvelope),
        (good[:30], errors.InvalidEnvelope),
        (setup.seal(5, owner=other.owner.username), errors.HeaderMismatch),
        (setup.seal(5, robot_id=str(other.robot.id)), errors.HeaderMismatch),
        (
            other.seal(5, owner=setup.owner.username, robot_id=str(setup.robot.id)),
            errors.UnknownKey,
        ),
        (bytes(tampered), errors.ForgedEnvelope),
        (bytes(key_id_forged), errors.ForgedEnvelope),
        (setup.seal(5, topic="/" + "x" * 300), errors.InvalidEnvelope),
        (setup.seal(5, topic="/odom\x00"), errors.InvalidEnvelope),
        (
            seal_for(setup.robot, setup.key, seq=5, time="1969-12-31T23:59:59Z"),
            errors.InvalidEnvelope,
        ),
    ]
    for data, error in cases:
        with pytest.raises(error):
            record_create(robot=setup.robot, data=data)
    assert _nothing_stored()
    setup.robot.refresh_from_db()
    assert setup.robot.last_seq == -1
    assert SecurityEvent.objects.filter(kind=SecurityEvent.Kind.FORGED_UPLOAD).count() == 2


def test_too_large_is_refused(make_robot, settings):
    setup = make_robot()
    settings.ENVELOPE_MAX_BYTES = 1000
    with pytest.raises(errors.EnvelopeTooLarge) as refused:
        record_create(robot=setup.robot, data=setup.seal(1, plaintext=b"x" * 2000))
    assert refused.value.http_status == 413
    assert _nothing_stored()


def test_replayed_or_stale_sequence_is_refused(make_robot):
    """The same envelope again is a replay (its 201 was lost: the agent counts it delivered);
    other data under a used or skipped seq is a conflict the owner hears about (a robot that
    lost its state, or its token and key in someone else's hands pushing the seq ahead)."""
    setup = make_robot()
    sent = setup.seal(7)
    record_create(robot=setup.robot, data=sent)
    with pytest.raises(errors.ReplayedSequence):
        record_create(robot=setup.robot, data=sent)
    assert not SecurityEvent.objects.exists()
    for seq in (7, 3):
        with pytest.raises(errors.SequenceConflict):
            record_create(robot=setup.robot, data=setup.seal(seq))
    assert Record.objects.count() == 1
    # The refused uploads' files (written before the sequence is checked) are gone again.
    root = Path(envelope_storage().location)
    assert [p.name for p in root.rglob("*.env")] == [f"{Record.objects.get().pk}.env"]
    events = SecurityEvent.objects.filter(kind=SecurityEvent.Kind.SEQUENCE_CONFLICT)
    assert sorted(e.detail["seq"] for e in events) == [3, 7]
    assert {e.owner for e in events} == {setup.owner}


def test_batch_is_all_or_nothing(make_robot):
    setup = make_robot()
    with pytest.raises(errors.InvalidEnvelope):
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(1), b"garbage"])
    with pytest.raises(errors.InvalidEnvelope):
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(2), setup.seal(2)])
    with pytest.raises(errors.InvalidEnvelope):
        record_create_batch(robot=setup.robot, envelopes=[])
    assert _nothing_stored()


def test_recently_rotated_key_is_accepted_then_expires(
    make_robot, django_capture_on_commit_callbacks
):
    setup = make_robot()
    with django_capture_on_commit_callbacks(execute=True):
        key_rotate(owner=setup.owner, sm4_key=sm4.generate_key())
    record_create(robot=setup.robot, data=setup.seal(1))
    setup.owner.keys.filter(is_current=False).update(retired_at=timezone.now() - timedelta(days=1))
    with pytest.raises(errors.UnknownKey):
        record_create(robot=setup.robot, data=setup.seal(2))


def _batch_left_nothing(setup) -> None:
    assert _nothing_stored()
    setup.robot.refresh_from_db()
    assert setup.robot.last_seq == -1  # unchanged: nothing was accepted


def test_a_batch_the_database_refuses_leaves_no_file_behind(make_robot, monkeypatch):
    setup = make_robot()

    def disk_full(*args, **kwargs):
        raise DatabaseError("disk full")

    monkeypatch.setattr(uploads_module._RECORD_ROWS, "insert", disk_full)
    with pytest.raises(DatabaseError):
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(seq) for seq in (1, 2, 3)])
    _batch_left_nothing(setup)


def test_a_batch_whose_third_file_fails_leaves_no_file_behind(make_robot, monkeypatch):
    setup = make_robot()
    real_write = storage_module.os.write
    written = []

    def fails_on_the_third(fd: int, data: bytes) -> int:
        if len(written) == 2:
            raise OSError(28, "No space left on device")
        written.append(fd)
        return real_write(fd, data)

    monkeypatch.setattr(storage_module.os, "write", fails_on_the_third)
    with pytest.raises(errors.StorageUnavailable) as refused:
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(seq) for seq in (1, 2, 3)])
    assert "No space" in str(refused.value.__cause__)
    assert refused.value.http_status == 503  # the robot keeps them and sends them again
    monkeypatch.undo()
    assert len(written) == 2
    _batch_left_nothing(setup)


def test_a_batch_whose_file_fails_in_the_writer_thread_leaves_no_file_behind(
    make_robot, monkeypatch
):
    """Files are written WRITE_CHUNK at a time beside the checks: a chunk that fails there
    refuses the upload (503) and takes the chunks written before it with it."""
    setup = make_robot()
    count = 2 * storage_module.WRITE_CHUNK + 5
    real_write = storage_module.os.write
    written = []

    def fails_in_the_second_chunk(fd: int, data: bytes) -> int:
        if len(written) == storage_module.WRITE_CHUNK + 3:
            raise OSError(28, "No space left on device")
        written.append(fd)
        return real_write(fd, data)

    envelopes = [setup.seal(seq) for seq in range(1, count + 1)]
    monkeypatch.setattr(storage_module.os, "write", fails_in_the_second_chunk)
    with pytest.raises(errors.StorageUnavailable) as refused:
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    assert refused.value.http_status == 503
    monkeypatch.undo()
    _batch_left_nothing(setup)


def test_a_batch_refused_after_files_were_written_leaves_no_file_behind(make_robot):
    """The last envelope names another robot: the files of those checked before it, written
    already, are removed with the refusal."""
    setup = make_robot()
    count = 2 * storage_module.WRITE_CHUNK + 5
    envelopes = [setup.seal(seq) for seq in range(1, count)]
    envelopes.append(setup.seal(count, robot_id="00000000-0000-4000-8000-000000000000"))
    with pytest.raises(errors.HeaderMismatch):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    _batch_left_nothing(setup)


def test_a_batch_of_more_than_a_chunk_is_stored_whole_with_the_rows_the_orm_reads(make_robot):
    """The rows go in as prepared tuples: read back through the ORM, each has its own
    columns, the defaults of a new record, one created_at, and its file."""
    setup = make_robot()
    count = 2 * storage_module.WRITE_CHUNK + 5
    envelopes = [setup.seal(seq, topic=f"/t{seq % 3}") for seq in range(1, count + 1)]
    before = timezone.now()
    returned = record_create_batch(robot=setup.robot, envelopes=envelopes)
    stored = list(Record.objects.order_by("seq"))
    assert [r.pk for r in stored] == [r.pk for r in returned]
    assert len({r.created_at for r in stored}) == 1
    assert before <= stored[0].created_at <= timezone.now()
    for record, data in zip(stored, envelopes, strict=True):
        header = envelope.read_header(data).header
        assert (record.topic, record.data_type, record.seq) == (
            header["topic"],
            header["type"],
            header["seq"],
        )
        assert record.captured_at.isoformat().replace("+00:00", "Z") == header["time"]
        assert (record.owner_id, record.robot_id) == (setup.owner.pk, setup.robot.pk)
        assert (record.digest, record.size) == (sm3.sm3_hex(data), len(data))
        assert (record.status, record.anchor_attempts, record.tx_hash) == ("pending", 0, "")
        assert (record.topic_seq, record.anchor_root_id, bytes(record.merkle_path)) == (
            None,
            None,
            b"",
        )
        assert record.deleted_at is None
        assert record.signer == ""
        with envelope_storage().open(record.storage_name) as stored_file:
            assert stored_file.read() == data


def test_without_syncfs_every_file_and_folder_is_fsynced(make_robot, monkeypatch):
    """Where there is no syncfs (not Linux), the batch fsyncs each file and its folder."""
    setup = make_robot()
    monkeypatch.setattr(files_module, "_SYNCFS", None)
    synced = []
    real_fsync = storage_module.fsync_path
    monkeypatch.setattr(
        storage_module, "fsync_path", lambda path: synced.append(path) or real_fsync(path)
    )
    records = record_create_batch(robot=setup.robot, envelopes=[setup.seal(seq) for seq in (1, 2)])
    files = {envelope_storage().path(record.storage_name) for record in records}
    assert set(synced) == files | {str(Path(next(iter(files))).parent)}
