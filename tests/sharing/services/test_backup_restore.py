"""Backup and restore (issue 12): `portal_backup` writes the database, the envelopes and the
secrets with a manifest of SM3 digests; `portal_restore`, run as its own process into a fresh
folder (a new SQLite file, new secrets and media folders) on the same chain, brings back a
portal on which every record verifies against the chain, and refuses a damaged backup or a
database that holds rows.

The chain is an anvil of the test's own (the session's is reverted under it after each test),
shared with the restore's processes: the restored portal must find the records, the owners' key
commitments and the grant on the chain the backup was taken on."""

import json
import os
import shutil
import stat
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from django.conf import settings as django_settings
from django.core.management import call_command
from django.urls import reverse

from accounts.keywrap import kek_fingerprint, master_key
from accounts.services.robots import robot_create
from chainworker import services as chain_services
from sharing.models import Grant, Record
from sharing.services import backup
from sharing.storage import envelope_storage
from stack.anvil import start_anvil
from tests.support.robot_setup import RobotSetup

pytestmark = pytest.mark.django_db

MANAGE = str(Path(django_settings.BASE_DIR) / "manage.py")


@pytest.fixture
def on_anvil(settings, isolated_portal):
    """The portal's chain is a real anvil node (zero gas, as `make run` starts it)."""
    with start_anvil(zero_gas=True) as node:
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()
        yield node
        chain_services._clients.clear()


@pytest.fixture
def portal_data(client, make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    """alice (two robots, four anchored records) granted bob access; bob's robot uploaded one."""
    alice = make_robot("alice")
    robot_b, token_b = robot_create(owner=alice.owner, name="robot-b")
    alice_b = RobotSetup(alice.owner, alice.key, robot_b, token_b)
    bob = make_robot("bob")
    for seq in (1, 2, 3):
        upload(alice, seq)
    upload(alice_b, 1)
    upload(bob, 1)
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    assert Grant.objects.get().status == Grant.Status.ACTIVE
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}
    return alice, bob


def _manage(folder: Path, chain_url: str, *args: str) -> subprocess.CompletedProcess:
    """`manage.py ARGS` as a separate portal whose every state lives in `folder`."""
    env = {
        **os.environ,
        "DJANGO_SETTINGS_MODULE": "portal.settings",
        "DATABASE_URL": f"sqlite:///{folder / 'db.sqlite3'}",
        "AUTHROS_VAR_DIR": str(folder),
        "AUTHROS_SECRETS_DIR": str(folder / "secrets"),
        "AUTHROS_MEDIA_ROOT": str(folder / "media"),
        "CHAIN_RPC_URL": chain_url,
        "REDIS_KEY_PREFIX": f"authros-restore-{uuid.uuid4().hex[:12]}",
    }
    for name in (
        "AUTHROS_MASTER_KEY",
        "CHAIN_OPERATOR_KEY",
        "AUTHROS_SM2_PRIVATE_KEY",
        "CHAIN_CONTRACT_ADDRESS",
        "ENVELOPE_STORAGE_URL",
    ):
        env.pop(name, None)
    return subprocess.run(
        [sys.executable, MANAGE, *args],
        env=env,
        cwd=django_settings.BASE_DIR,
        capture_output=True,
        text=True,
        timeout=300,
    )


VERIFY_ALL = """
import json
from sharing.models import Grant, Record
from sharing.verification.check import records_verify
def outcome(record, viewer_id):
    return records_verify(record_ids=[record.id], viewer_id=viewer_id)[0].verdict.outcome
outcomes = {str(record.id): outcome(record, record.owner_id) for record in Record.objects.all()}
for grant in Grant.objects.all():
    for record in Record.objects.filter(owner=grant.owner):
        outcomes[f"{record.id} as {grant.grantee.username}"] = outcome(record, grant.grantee_id)
print(json.dumps(outcomes))
"""


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.process
def test_a_backup_restored_into_a_fresh_folder_verifies_every_record(
    on_anvil, portal_data, tmp_path
):
    alice, _bob = portal_data
    folder = tmp_path / "backup"
    call_command("portal_backup", to=str(folder))

    # A 0700 folder of 0600 files, and a manifest without a secret in it.
    manifest = json.loads((folder / "manifest.json").read_text())
    assert _mode(folder) == 0o700
    assert _mode(folder / "secrets") == 0o700
    for path in folder.rglob("*"):
        if path.is_file():
            assert _mode(path) == 0o600, path
    assert set(manifest["secrets"]["files"]) >= {"master.key", "operator.key"}
    text = (folder / "manifest.json").read_text()
    for name in manifest["secrets"]["files"]:
        secret = (Path(django_settings.SECRETS_DIR) / name).read_text().strip()
        assert secret not in text
    assert manifest["kek_fingerprint"] == kek_fingerprint(master_key())
    assert manifest["database"]["counts"]["sharing.record"] == 5
    assert manifest["database"]["counts"]["sharing.grant"] == 1
    assert manifest["envelopes"]["count"] == 5
    assert manifest["written_during_backup"] == []
    assert manifest["records_without_envelope"] == []
    for record in Record.objects.all():
        assert manifest["envelopes"]["files"][record.storage_name]["sm3"] == record.digest

    fresh = tmp_path / "restored"
    fresh.mkdir()
    migrated = _manage(fresh, on_anvil.url, "migrate", "--no-input")
    assert migrated.returncode == 0, migrated.stderr

    # A tampered envelope in the backup is refused before anything changes.
    tampered = tmp_path / "tampered"
    shutil.copytree(folder, tampered)
    victim = Record.objects.filter(owner=alice.owner).first()
    envelope = tampered / "envelopes" / victim.storage_name
    data = bytearray(envelope.read_bytes())
    data[-1] ^= 0x01
    envelope.write_bytes(bytes(data))
    refused = _manage(fresh, on_anvil.url, "portal_restore", "--from", str(tampered))
    assert refused.returncode != 0
    assert "damaged" in refused.stderr
    assert victim.storage_name in refused.stderr
    assert not (fresh / "media" / "envelopes").exists() or not any(
        p.is_file() for p in (fresh / "media" / "envelopes").rglob("*")
    )

    restored = _manage(fresh, on_anvil.url, "portal_restore", "--from", str(folder))
    assert restored.returncode == 0, restored.stderr
    assert "5 records" in restored.stdout
    for name in manifest["secrets"]["files"]:
        restored_secret = fresh / "secrets" / name
        assert restored_secret.read_bytes() == (folder / "secrets" / name).read_bytes()
        assert _mode(restored_secret) == 0o600
    for secret_text in (
        (folder / "secrets" / name).read_text().strip() for name in manifest["secrets"]["files"]
    ):
        assert secret_text not in restored.stdout + restored.stderr

    verified = _manage(fresh, on_anvil.url, "shell", "-c", VERIFY_ALL)
    assert verified.returncode == 0, verified.stderr
    outcomes = json.loads(verified.stdout.strip().splitlines()[-1])
    assert len(outcomes) == 5 + 4  # every record by its owner, alice's four by bob too
    assert set(outcomes.values()) == {"verified"}, outcomes

    # The restored portal backs up again, from its own SQLite file outside any test transaction.
    second = tmp_path / "second"
    again_backed = _manage(fresh, on_anvil.url, "portal_backup", "--to", str(second))
    assert again_backed.returncode == 0, again_backed.stderr
    second_manifest = json.loads((second / "manifest.json").read_text())
    assert second_manifest["database"]["counts"]["sharing.record"] == 5
    assert second_manifest["envelopes"]["files"] == manifest["envelopes"]["files"]
    assert second_manifest["kek_fingerprint"] == manifest["kek_fingerprint"]

    # Once restored, the database holds rows: a second restore is refused without --force.
    again = _manage(fresh, on_anvil.url, "portal_restore", "--from", str(folder))
    assert again.returncode != 0
    assert "not empty" in again.stderr
    forced = _manage(fresh, on_anvil.url, "portal_restore", "--from", str(folder), "--force")
    assert forced.returncode == 0, forced.stderr


def test_records_written_during_the_backup_are_listed(make_robot, upload, tmp_path, monkeypatch):
    robot = make_robot("carol")
    first = upload(robot, 1)
    copy_envelopes = backup._copy_envelopes
    late: list[Record] = []

    def copy_after_an_upload(storage, into):
        # An upload lands after the database snapshot, before the files are copied.
        late.append(upload(robot, 2, anchor=False))
        return copy_envelopes(storage, into)

    monkeypatch.setattr(backup, "_copy_envelopes", copy_after_an_upload)
    manifest = backup.portal_backup(to=tmp_path / "backup")
    assert manifest["database"]["counts"]["sharing.record"] == 1
    assert manifest["written_during_backup"] == [str(late[0].id)]
    assert manifest["envelopes_without_record"] == [late[0].storage_name]
    assert first.storage_name in manifest["envelopes"]["files"]


def test_a_backup_goes_into_a_new_folder_and_a_restore_needs_a_manifest(make_robot, tmp_path):
    make_robot("dave")
    used = tmp_path / "used"
    used.mkdir()
    (used / "something").write_text("kept")
    with pytest.raises(backup.BackupRefused, match="not empty"):
        backup.portal_backup(to=used)
    assert (used / "something").read_text() == "kept"
    with pytest.raises(backup.BackupRefused, match="manifest"):
        backup.portal_restore(source=used)


def test_a_restore_into_a_database_with_rows_is_refused_and_changes_nothing(
    make_robot, upload, tmp_path
):
    robot = make_robot("erin")
    record = upload(robot, 1)
    folder = tmp_path / "backup"
    backup.portal_backup(to=folder)
    stored = envelope_storage()
    stored.delete(record.storage_name)
    with pytest.raises(backup.BackupRefused, match="not empty"):
        backup.portal_restore(source=folder)
    assert not stored.exists(record.storage_name)
