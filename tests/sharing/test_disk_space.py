"""A disk that uploads are written to never fills up unnoticed: an upload that would leave it
below STORAGE_MIN_FREE_BYTES is refused and stores nothing (the robot spools it), and the
operator is alerted while it is below STORAGE_LOW_FREE_BYTES. Thresholds are set around the
real free space of this machine's disk; nothing is faked."""

import os
from pathlib import Path

import pytest

from chainworker.models import OperatorAlert
from core.files import filesystem_free
from core.storage_url import envelope_storage_config
from portal.celery import app as celery_app
from sharing import disk
from sharing.disk import DISK_LOW_ALERT, disk_space_watch, portal_disks
from sharing.exports.create import export_create
from sharing.exports.files import EXPORT_STORAGE_PREFIX
from sharing.exports.run import export_run
from sharing.models import Export, Record
from sharing.services.uploads import record_create
from sharing.storage import envelope_storage
from tests.api.conftest import RECORDS, Snapshot, b64, token_client
from tests.support.logs import logged_by

pytestmark = pytest.mark.django_db

GIB = 1024**3


def _free() -> int:
    return min(filesystem_free(folder) for folder in portal_disks())


def test_the_disks_are_the_envelope_folder_and_the_sqlite_database(settings):
    folders = portal_disks()
    assert Path(settings.MEDIA_ROOT).absolute() in [folder.parent for folder in folders]
    name = settings.DATABASES["default"]["NAME"]
    if settings.DATABASES["default"]["ENGINE"].endswith("sqlite3"):
        assert len(folders) == 2
    else:  # PostgreSQL's disk is its server's, not this host's
        assert len(folders) == 1, name


def test_an_s3_bucket_is_no_disk_of_this_host(settings, tmp_path):
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": envelope_storage_config(
            "s3://envelopes", media_root=tmp_path, endpoint_url="http://127.0.0.1:9", region=""
        ),
    }
    assert Path(settings.MEDIA_ROOT).absolute() not in [f.parent for f in portal_disks()]


def test_an_upload_that_would_leave_the_disk_nearly_full_is_refused_and_stores_nothing(
    make_robot, settings, monkeypatch
):
    setup = make_robot()
    robot = token_client(setup.token)
    monkeypatch.setitem(disk._refusals_logged, "at", float("-inf"))
    settings.STORAGE_MIN_FREE_BYTES = _free() + GIB
    snapshot = Snapshot()
    with logged_by("sharing.disk") as logged:
        answer = robot.post(RECORDS, {"envelope": b64(setup.seal(1))}, format="json")
        again = robot.post(RECORDS, {"envelopes": [b64(setup.seal(1))]}, format="json")
    assert answer.status_code == 503, answer.content
    assert answer.json()["error"] == "storage_unavailable"
    assert "nearly full" in answer.json()["detail"]
    assert answer["Retry-After"] == "60"
    assert again.status_code == 503
    assert snapshot.unchanged()
    # Logged once, not once per refused upload (a full disk must not fill with log lines).
    refusals = [r for r in logged if "uploads refused" in r.getMessage()]
    assert len(refusals) == 1
    assert "STORAGE_MIN_FREE_BYTES" in refusals[0].getMessage()

    # Room again: the robot's resend is taken.
    settings.STORAGE_MIN_FREE_BYTES = max(_free() - GIB, 0)
    answer = robot.post(RECORDS, {"envelope": b64(setup.seal(1))}, format="json")
    assert answer.status_code == 201, answer.content
    assert Record.objects.filter(robot=setup.robot, seq=1).exists()


def test_the_upload_s_own_size_counts(make_robot, settings, monkeypatch):
    """The floor is what the upload would leave: a batch bigger than the room above the floor
    is refused though the disk is above the floor now."""
    setup = make_robot()
    envelopes = [b64(setup.seal(seq, plaintext=os.urandom(60_000))) for seq in range(1, 101)]
    size = 100 * 60_000
    # The disks' free room as read now, held: other test processes write and delete files on
    # the same disk meanwhile (once more than the 4.5 MB of this test's margin).
    free = _free()
    monkeypatch.setattr(disk, "filesystem_free", lambda folder: free)
    # The batch is 6 MB; 1.5 MB of room above the floor.
    settings.STORAGE_MIN_FREE_BYTES = free - size // 4
    answer = token_client(setup.token).post(RECORDS, {"envelopes": envelopes}, format="json")
    assert answer.status_code == 503, answer.content
    assert not Record.objects.filter(robot=setup.robot).exists()


def test_an_export_is_refused_too_and_leaves_no_files(make_robot, settings):
    """An owner's export writes a copy of many records: it must not fill the disk either."""
    setup = make_robot()
    record_create(robot=setup.robot, data=setup.seal(1))
    settings.STORAGE_MIN_FREE_BYTES = _free() + GIB
    export = export_run(export_id=export_create(requester=setup.owner).pk)
    assert export.status == Export.Status.FAILED
    assert "nearly full" in export.error
    assert not envelope_storage().exists(f"{EXPORT_STORAGE_PREFIX}/{export.pk}")


def test_zero_never_refuses(make_robot, settings):
    setup = make_robot()
    settings.STORAGE_MIN_FREE_BYTES = 0
    answer = token_client(setup.token).post(
        RECORDS, {"envelope": b64(setup.seal(1))}, format="json"
    )
    assert answer.status_code == 201


def test_the_operator_is_alerted_while_a_disk_is_low_and_the_alert_resolves(settings):
    settings.STORAGE_LOW_FREE_BYTES = _free() + GIB
    free_of = disk_space_watch()
    assert set(free_of) == {str(folder) for folder in portal_disks()}
    alerts = OperatorAlert.objects.filter(kind=DISK_LOW_ALERT, resolved_at=None)
    assert sorted(alerts.values_list("subject", flat=True)) == sorted(free_of)
    alert = alerts.first()
    assert alert.detail["free_bytes"] == free_of[alert.subject]
    assert alert.detail["alert_below_bytes"] == settings.STORAGE_LOW_FREE_BYTES

    disk_space_watch()  # still low: the same alerts, seen again
    assert OperatorAlert.objects.filter(kind=DISK_LOW_ALERT).count() == len(free_of)

    settings.STORAGE_LOW_FREE_BYTES = 0
    disk_space_watch()
    assert not OperatorAlert.objects.filter(kind=DISK_LOW_ALERT, resolved_at=None).exists()
    assert OperatorAlert.objects.filter(kind=DISK_LOW_ALERT).count() == len(free_of)


def test_a_disk_with_room_raises_no_alert(settings):
    settings.STORAGE_LOW_FREE_BYTES = 1
    disk_space_watch()
    assert not OperatorAlert.objects.filter(kind=DISK_LOW_ALERT).exists()


def test_a_long_folder_name_fits_an_alert(settings, tmp_path):
    deep = tmp_path.joinpath(*["a-rather-long-folder-name"] * 8)
    settings.MEDIA_ROOT = deep
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": envelope_storage_config("", media_root=deep, endpoint_url="", region=""),
    }
    settings.STORAGE_LOW_FREE_BYTES = _free() + GIB
    disk_space_watch()
    subjects = OperatorAlert.objects.filter(kind=DISK_LOW_ALERT).values_list("subject", flat=True)
    longest = max(subjects, key=len)
    assert len(longest) <= 100
    assert longest.endswith("a-rather-long-folder-name/envelopes")


def test_a_folder_made_on_first_use_counts_its_parent_s_disk(tmp_path):
    not_yet = tmp_path / "not" / "made" / "yet"
    assert abs(filesystem_free(not_yet) - filesystem_free(tmp_path)) < GIB // 16


@pytest.mark.parametrize("name", ["watch-disk-space"])
def test_the_beat_runs_the_watch(settings, name):
    entry = settings.CELERY_BEAT_SCHEDULE[name]
    assert entry["task"] in celery_app.tasks
    assert entry["schedule"] > 0
