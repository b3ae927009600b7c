"""Issue 37.1: an export is stored sealed (never plaintext at rest, in backups neither) and is
downloadable only while its requester may still view every record in it. A revocation, a grant
that expired, a narrowed grant, a deleted record or a closed account withdraws it: the download
answers 410 `export_withdrawn` with the reason and streams nothing, and the files leave the
storage with the key that opened them. Rebuilding it exports what may be viewed now.
"""

import json
from datetime import timedelta
from pathlib import Path

import pytest
from django.core.files.base import ContentFile
from django.urls import reverse
from django.utils import timezone

from accounts.models import Owner
from sharing.exports.create import export_create
from sharing.exports.withdraw import exports_sweep
from sharing.grant_terms import grant_terms_make
from sharing.models import Export, ExportRecord, Grant, Record
from sharing.services.backup import portal_backup
from sharing.services.deletion import account_delete, records_delete
from sharing.services.grants import grant_create, grant_revoke, grant_terms_change
from sharing.services.uploads import record_create_batch
from sharing.storage import envelope_storage
from smcrypto.stream import MAGIC as SEALED_MAGIC
from tests.api.conftest import session_client
from tests.authros_verify.conftest import export_files
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

MCAP_MAGIC = b"\x89MCAP0\r\n"
SECRET = "the-plaintext-nobody-may-read-at-rest"


def fig4(topic: str, n: int) -> bytes:
    record = {"K": {"data": f"{SECRET} {n}"}, "Owner": "alice", "Type": "std_msgs/String"}
    return json.dumps({**record, "Topic": topic}).encode()


@pytest.fixture
def shared(alice, bob, django_capture_on_commit_callbacks) -> list[Record]:
    """Alice's four anchored String records on two topics; bob holds her grant to all."""
    envelopes = [
        alice.seal(
            n,
            topic=topic,
            data_type="std_msgs/String",
            time=f"2026-05-01T12:00:0{n}Z",
            plaintext=fig4(topic, n),
        )
        for n, topic in enumerate(["/chatter", "/chatter", "/other", "/other"], start=1)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=alice.robot, envelopes=envelopes)
    return records


def exported(requester: Owner, capture, **selection) -> Export:
    with capture(execute=True):
        export = export_create(requester=requester, **selection)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    return export


def stored(export: Export) -> list[bytes]:
    storage = envelope_storage()
    return [storage.open(name, "rb").read() for name in (export.mcap_name, export.bundle_name)]


def assert_withdrawn(export: Export, requester: Owner, why: str) -> None:
    """Refused with the reason, nothing streamed; the files and the key are gone."""
    api = session_client(requester)
    for part in ("mcap", "bundle"):
        answer = api.get(f"/api/v1/exports/{export.pk}/{part}/")
        assert answer.status_code == 410, answer.content
        assert answer.json()["error"] == "export_withdrawn"
        assert why in answer.json()["detail"]
    export.refresh_from_db()
    assert export.status == Export.Status.WITHDRAWN
    assert why in export.error
    assert bytes(export.key_wrapped) == b""
    storage = envelope_storage()
    assert not storage.exists(export.mcap_name)
    assert not storage.exists(export.bundle_name)
    assert not ExportRecord.objects.filter(export=export).exists()
    page = api.get(reverse("export-detail", args=[export.pk])).content.decode()
    assert 'data-testid="export-withdrawn"' in page
    assert why in page


def test_the_files_at_rest_are_sealed_and_open_only_as_downloaded(
    alice, shared, django_capture_on_commit_callbacks
):
    export = exported(alice.owner, django_capture_on_commit_callbacks)
    for data in stored(export):
        assert data.startswith(SEALED_MAGIC)
        assert MCAP_MAGIC not in data
        assert SECRET.encode() not in data
        assert b"records" not in data
    mcap, bundle = export_files(export)
    assert mcap.startswith(MCAP_MAGIC)
    assert SECRET.encode() in mcap
    assert json.loads(bundle)["export"] == str(export.pk)
    answer = session_client(alice.owner).get(f"/api/v1/exports/{export.pk}/mcap/")
    assert answer.status_code == 200
    assert answer["Content-Length"] == str(len(mcap))
    assert b"".join(answer.streaming_content) == mcap


def test_a_backup_holds_no_plaintext_export_and_none_once_withdrawn(
    alice, shared, tmp_path: Path, django_capture_on_commit_callbacks
):
    export = exported(alice.owner, django_capture_on_commit_callbacks)
    portal_backup(to=tmp_path / "before")
    copies = list((tmp_path / "before" / "envelopes" / "exports").rglob("*"))
    files = [path for path in copies if path.is_file()]
    assert len(files) == 2
    for path in files:
        data = path.read_bytes()
        assert MCAP_MAGIC not in data
        assert SECRET.encode() not in data

    with django_capture_on_commit_callbacks(execute=True):
        records_delete(owner=alice.owner, actor=alice.owner.user, record_ids=[shared[0].pk])
    portal_backup(to=tmp_path / "after")
    assert not (tmp_path / "after" / "envelopes" / "exports" / str(export.pk)).exists()
    dump = (tmp_path / "after" / "database.json").read_text()
    assert SECRET not in dump


def test_revocation_withdraws_the_grantees_export_at_once(
    alice, bob, shared, django_capture_on_commit_callbacks
):
    export = exported(bob, django_capture_on_commit_callbacks)
    assert export.exported == 4
    assert session_client(bob).get(f"/api/v1/exports/{export.pk}/mcap/").status_code == 200
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=alice.owner, grantee=bob)
    # Withdrawn by the recheck queued on commit, before any download asks.
    export.refresh_from_db()
    assert export.status == Export.Status.WITHDRAWN
    assert_withdrawn(export, bob, "alice revoked your access")
    # Rebuilding it under bob's access now: nothing of alice's is his to export.
    answer = session_client(bob).post(f"/api/v1/exports/{export.pk}/rebuild/")
    assert answer.status_code == 400
    assert answer.json()["error"] == "invalid_selection"


def test_an_expired_grant_refuses_the_download_and_the_sweep_removes_the_files(
    alice, make_owner, shared, django_capture_on_commit_callbacks
):
    carol = make_owner("carol")
    terms = grant_terms_make(owner=alice.owner, expires_at=timezone.now() + timedelta(hours=1))
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=carol, terms=terms)
    kept = exported(carol, django_capture_on_commit_callbacks)
    swept = exported(carol, django_capture_on_commit_callbacks)
    # The grant runs out after the exports were made (as time passing would).
    Grant.objects.filter(grantee=carol).update(expires_at=timezone.now() - timedelta(seconds=1))
    assert_withdrawn(kept, carol, "your grant from alice expired")
    assert exports_sweep()["withdrawn"] == 1
    assert_withdrawn(swept, carol, "your grant from alice expired")


def test_a_narrowed_grant_withdraws_an_export_it_no_longer_covers(
    alice, bob, shared, django_capture_on_commit_callbacks
):
    inside = exported(bob, django_capture_on_commit_callbacks, topics=["/chatter"])
    everything = exported(bob, django_capture_on_commit_callbacks)
    terms = grant_terms_make(owner=alice.owner, topics=["/chatter"])
    with django_capture_on_commit_callbacks(execute=True):
        grant_terms_change(owner=alice.owner, grantee=bob, terms=terms)
    assert_withdrawn(everything, bob, "alice narrowed your grant")
    # The export of /chatter only is still inside the grant: not withdrawn by the change.
    inside.refresh_from_db()
    assert inside.status == Export.Status.DONE


def test_a_deleted_record_leaves_every_export_that_held_it(
    alice, bob, shared, django_capture_on_commit_callbacks
):
    own = exported(alice.owner, django_capture_on_commit_callbacks)
    granted = exported(bob, django_capture_on_commit_callbacks)
    other = exported(alice.owner, django_capture_on_commit_callbacks, topics=["/other"])
    with django_capture_on_commit_callbacks(execute=True):
        records_delete(owner=alice.owner, actor=alice.owner.user, record_ids=[shared[0].pk])
    assert_withdrawn(own, alice.owner, "a record in it was deleted")
    assert_withdrawn(granted, bob, "a record in it was deleted")
    other.refresh_from_db()
    assert other.status == Export.Status.DONE  # it never held the deleted record

    # Rebuilt: the same selection, without the deleted record.
    client = session_client(alice.owner)
    with django_capture_on_commit_callbacks(execute=True):
        answer = client.post(reverse("export-rebuild", args=[own.pk]))
    assert answer.status_code == 302
    rebuilt = Export.objects.exclude(pk__in=[own.pk, granted.pk, other.pk]).get()
    assert (rebuilt.status, rebuilt.exported) == (Export.Status.DONE, 3)
    mcap, _bundle = export_files(rebuilt)
    assert f"{SECRET} 1".encode() not in mcap


def test_a_closed_account_withdraws_its_exports(
    alice, bob, shared, django_capture_on_commit_callbacks
):
    granted = exported(bob, django_capture_on_commit_callbacks)
    with django_capture_on_commit_callbacks(execute=True):
        account_delete(owner=alice.owner, password=TEST_PASSWORD)
    granted.refresh_from_db()
    assert granted.status == Export.Status.WITHDRAWN
    assert not envelope_storage().exists(granted.mcap_name)


def test_an_export_stored_before_sealing_is_withdrawn_and_its_plaintext_removed(
    alice, shared, django_capture_on_commit_callbacks
):
    export = exported(alice.owner, django_capture_on_commit_callbacks)
    # As an export made by the code before issue 37 left it: plaintext files, no key.
    storage = envelope_storage()
    storage.delete(export.mcap_name)
    storage.save(export.mcap_name, ContentFile(MCAP_MAGIC + SECRET.encode()))
    Export.objects.filter(pk=export.pk).update(key_wrapped=b"")
    assert exports_sweep()["withdrawn"] == 1
    export.refresh_from_db()
    assert export.status == Export.Status.WITHDRAWN
    assert "stored before exports were sealed" in export.error
    assert not storage.exists(export.mcap_name)


def test_the_requesters_closed_account_withdraws_their_exports(
    alice, bob, shared, django_capture_on_commit_callbacks
):
    granted = exported(bob, django_capture_on_commit_callbacks)
    with django_capture_on_commit_callbacks(execute=True):
        account_delete(owner=bob, password=TEST_PASSWORD)
    granted.refresh_from_db()
    assert granted.status == Export.Status.WITHDRAWN
    assert bytes(granted.key_wrapped) == b""
    assert not envelope_storage().exists(granted.bundle_name)
