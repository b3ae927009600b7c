"""An upload is answered only once its rows would survive a power loss: on SQLite (WAL,
synchronous=NORMAL) a sync of the database's file system that started after the upload's
transaction closed; PostgreSQL is durable at commit."""

import os

import pytest
from django.db import connection

from core import commits as commits_module
from core import files as files_module
from sharing import errors
from sharing.models import Record
from sharing.services.uploads import record_create_batch

pytestmark = pytest.mark.django_db


class _RecordingSyncfs:
    """syncfs(2) that records the folder it was asked for, the rows of the robot then in the
    database and how deep the connection's atomic blocks were."""

    def __init__(self, robot) -> None:
        self.robot = robot
        self.calls: list[tuple[str, int, int]] = []

    def __call__(self, fd: int) -> int:
        folder = os.readlink(f"/proc/self/fd/{fd}")
        rows = Record.objects.filter(robot=self.robot).count()
        self.calls.append((folder, rows, len(connection.atomic_blocks)))
        return 0


@pytest.fixture
def recording_syncfs(monkeypatch, make_robot):
    setup = make_robot()
    syncfs = _RecordingSyncfs(setup.robot)
    monkeypatch.setattr(files_module, "_SYNCFS", syncfs)
    monkeypatch.setattr(files_module, "_sync_groups", {})
    return setup, syncfs


def _database_folder() -> str:
    return os.path.dirname(os.path.abspath(connection.settings_dict["NAME"]))


def test_an_upload_returns_after_its_committed_rows_were_synced(recording_syncfs):
    setup, syncfs = recording_syncfs
    depth = len(connection.atomic_blocks)

    record_create_batch(robot=setup.robot, envelopes=[setup.seal(seq) for seq in (1, 2)])

    database_syncs = [call for call in syncfs.calls if call[0] == _database_folder()]
    if connection.vendor != "sqlite":
        assert database_syncs == []  # durable at commit
        return
    # The envelope files' sync comes first (before the rows exist), the database's last:
    # after both rows were written and the upload's own transaction had closed.
    assert syncfs.calls[-1] == (_database_folder(), 2, depth)
    assert syncfs.calls[0][1] == 0


def test_without_syncfs_the_write_ahead_log_is_fsynced(monkeypatch, make_robot):
    setup = make_robot()
    monkeypatch.setattr(files_module, "_SYNCFS", None)
    synced = []
    monkeypatch.setattr(commits_module, "fsync_path", synced.append)

    record_create_batch(robot=setup.robot, envelopes=[setup.seal(1)])

    if connection.vendor != "sqlite":
        assert synced == []
        return
    database = os.path.abspath(connection.settings_dict["NAME"])
    wal = f"{database}-wal"
    assert synced == [wal if os.path.exists(wal) else database]


def test_a_sync_that_fails_asks_the_robot_to_send_again_and_keeps_what_was_stored(
    monkeypatch, make_robot
):
    """The rows are committed: their files stay, and the robot's second try is answered
    replayed_sequence, which it counts delivered."""
    setup = make_robot()
    envelope = setup.seal(1)

    def failing(using="default"):
        raise OSError("I/O error")

    monkeypatch.setattr("sharing.services.uploads.commits_durable", failing)
    with pytest.raises(errors.StorageUnavailable) as refused:
        record_create_batch(robot=setup.robot, envelopes=[envelope])
    assert refused.value.http_status == 503
    (record,) = Record.objects.filter(robot=setup.robot)
    assert record.seq == 1
    monkeypatch.undo()
    with pytest.raises(errors.ReplayedSequence):
        record_create_batch(robot=setup.robot, envelopes=[envelope])
