"""Deleting records and accounts, and the retention policy (sharing/services/deletion.py): what goes
(the ciphertext, from storage and cache), what stays (the tombstone, the digest, the proof),
who may, and a crash between the two steps."""

from datetime import UTC, datetime, timedelta

import pytest
from django.test import Client
from django.urls import reverse

from accounts.errors import UsernameTaken, WrongPassword
from accounts.models import AccountEvent, OwnerToken, Robot
from accounts.services.owners import owner_create
from accounts.services.robots import robot_create, robot_retention_set
from chainworker.services import chain_client
from sharing.cache import envelope_cache_get
from sharing.errors import (
    NotDeletableYet,
    NotRecordOwner,
    OwnerNotFound,
    RecordDeleted,
    RecordNotFound,
)
from sharing.models import Grant, Record, Verdict
from sharing.selectors.grants import owner_resolve
from sharing.services.deletion import (
    account_delete,
    record_delete,
    records_delete,
    records_purge,
    retention_apply,
)
from sharing.services.grants import grant_create
from sharing.storage import envelope_storage
from sharing.verification.check import records_verify
from sharing.verification.opening import record_open
from smcrypto import sm4
from tests.api.conftest import RECORDS, token_client
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup

pytestmark = pytest.mark.django_db


def days_ago(days: float) -> str:
    return (datetime.now(tz=UTC) - timedelta(days=days)).isoformat().replace("+00:00", "Z")


def stored(record: Record) -> bool:
    return envelope_storage().exists(record.storage_name)


def second_robot(setup: RobotSetup, name: str = "second") -> RobotSetup:
    robot, token = robot_create(owner=setup.owner, name=name)
    return RobotSetup(setup.owner, setup.key, robot, token)


def fresh(record: Record) -> Record:
    record.refresh_from_db()
    return record


def assert_purged(record: Record, *, reason: str) -> None:
    record = fresh(record)
    assert record.is_deleted
    assert record.purged_at is not None
    assert record.deletion_reason == reason
    assert not stored(record)
    assert envelope_cache_get(record.id) is None


def assert_live(record: Record) -> None:
    record = fresh(record)
    assert not record.is_deleted
    assert record.purged_at is None
    assert stored(record)


def test_retention_removes_exactly_what_it_should(make_robot, upload, alice):
    carol = make_robot("carol")
    other_robot = second_robot(alice)
    robot_retention_set(robot=alice.robot, days=30, actor=alice.owner.user)
    robot_retention_set(robot=carol.robot, days=60, actor=carol.owner.user)
    expired = [upload(alice, seq, time=days_ago(40 + seq)) for seq in (1, 2, 3)]
    recent = upload(alice, 4, time=days_ago(29))
    no_retention = upload(other_robot, 1, time=days_ago(400))
    within_window = upload(carol, 1, time=days_ago(40))
    failed = upload(alice, 5, time=days_ago(50))
    Record.objects.filter(pk=failed.pk).update(status=Record.Status.FAILED)
    pending = upload(alice, 6, time=days_ago(50), anchor=False)
    assert {fresh(r).status for r in [*expired, recent]} == {Record.Status.ANCHORED}
    assert envelope_cache_get(expired[0].id) is not None  # cached on upload

    assert retention_apply() == {"deleted": 3, "purged": 3, "kept_not_anchored": 2}

    for record in expired:
        assert_purged(record, reason=Record.Deletion.RETENTION)
        assert fresh(record).deleted_by is None  # the policy, not a person
        assert fresh(record).digest == record.digest  # the tombstone keeps its digest
    for record in (recent, no_retention, within_window, failed, pending):
        assert_live(record)
    event = AccountEvent.objects.get(owner=alice.owner, kind=AccountEvent.Kind.RECORDS_DELETED)
    assert event.detail == {"records": 3, "by": "retention policy"}
    assert not AccountEvent.objects.filter(
        owner=carol.owner, kind=AccountEvent.Kind.RECORDS_DELETED
    ).exists()
    # Idempotent: a second run finds nothing more to do.
    assert retention_apply() == {"deleted": 0, "purged": 0, "kept_not_anchored": 2}


def test_retention_runs_in_batches_and_one_run_at_a_time(settings, alice, upload, redis_client):
    settings.RETENTION_BATCH = 2
    settings.RETENTION_MAX_BATCHES = 2
    records = [upload(alice, seq, time=days_ago(10)) for seq in range(1, 6)]
    robot_retention_set(robot=alice.robot, days=1, actor=alice.owner.user)
    assert retention_apply()["deleted"] == 4  # two batches of two: the next run goes on
    assert retention_apply()["deleted"] == 1
    for record in records:
        assert_purged(record, reason=Record.Deletion.RETENTION)
    # Another run holding the lock (another worker, another beat): this one does nothing.
    lock = redis_client.lock(f"{settings.REDIS_KEY_PREFIX}:work:retention", timeout=60)
    assert lock.acquire(blocking=False)
    try:
        assert retention_apply() == {"skipped": 1}
    finally:
        lock.release()


def test_only_the_owner_deletes_and_a_deleted_record_stays_a_tombstone(
    alice,
    bob,
    make_owner,
    upload,
    make_owner_token,
    django_capture_on_commit_callbacks,
    monkeypatch,
):
    carol = make_owner("carol")
    record, other = upload(alice, 1), upload(alice, 2)
    pending = upload(alice, 3, anchor=False)
    with pytest.raises(NotRecordOwner):
        record_delete(owner=bob, record_id=record.id, actor=bob.user)  # a grantee
    with pytest.raises(RecordNotFound):
        record_delete(owner=carol, record_id=record.id, actor=carol.user)  # another owner
    with pytest.raises(NotDeletableYet):
        record_delete(owner=alice.owner, record_id=pending.id, actor=alice.owner.user)
    # The API says the same: 403 for a grantee, 404 for a stranger, 409 while pending; an
    # owner token needs the `delete` scope, a robot token never deletes.
    url = f"{RECORDS}{record.id}/"
    _, bobs = make_owner_token(bob, scopes=("read", "delete"))
    _, carols = make_owner_token(carol, scopes=("delete",))
    _, read_only = make_owner_token(alice.owner, scopes=("read",))
    _, deleter = make_owner_token(alice.owner, scopes=("read", "delete"))
    for key, status, error in [
        (bobs, 403, "not_record_owner"),
        (carols, 404, "not_found"),
        (read_only, 403, "insufficient_scope"),
        (alice.token, 403, "permission_denied"),
    ]:
        answer = token_client(key).delete(url)
        assert (answer.status_code, answer.json()["error"]) == (status, error)
    answer = token_client(deleter).delete(f"{RECORDS}{pending.id}/")
    assert (answer.status_code, answer.json()["error"]) == (409, "not_anchored_yet")
    assert_live(record)
    assert_live(pending)

    with django_capture_on_commit_callbacks(execute=True):
        answer = token_client(deleter).delete(url)
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert body["deleted_by"] == alice.owner.username
    assert body["deletion_reason"] == "owner"
    assert body["deleted_at"]
    assert_purged(record, reason=Record.Deletion.OWNER)
    assert token_client(deleter).delete(url).json()["deleted_at"] == body["deleted_at"]
    # Lists hide it unless asked for; its metadata and proof stay; its content is 410.
    reader = token_client(deleter)
    assert [r["id"] for r in reader.get(RECORDS).json()["results"]] == [
        str(pending.id),
        str(other.id),
    ]
    listed = reader.get(RECORDS, {"status": "deleted"}).json()["results"]
    assert [r["id"] for r in listed] == [str(record.id)]
    assert reader.get(url).json()["deletion_reason"] == "owner"
    proof = reader.get(f"{url}proof/")
    assert proof.status_code == 200
    assert proof.json()["digest"] == "0x" + record.digest
    for key in (deleter, bobs):
        content = token_client(key).get(f"{url}content/")
        assert (content.status_code, content.json()["error"]) == (410, "record_deleted")
    # The record page: "deleted" with when and by whom, never TAMPERED, never a 500.
    client = Client()
    client.force_login(bob.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 410
    text = page.content.decode()
    assert 'data-verdict="deleted"' in text
    assert f"by {alice.owner.username}" in text
    assert "TAMPERED" not in text
    assert client.get(reverse("record-raw", args=[record.id])).status_code == 410
    # The digest stays on chain (root mode: the root its proof folds to).
    root = fresh(record).anchor_root.root
    assert chain_client().root_of(alice.owner.eoa_address, bytes.fromhex(root))
    assert record_open(record_id=other.id, viewer=bob).plaintext  # the others are untouched
    _crash_between_tombstone_and_purge(alice, bob, upload, monkeypatch)


def test_deleting_an_account_end_to_end(
    alice, bob, make_owner, upload, make_owner_token, django_capture_on_commit_callbacks
):
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=bob, grantee=alice.owner)
    anchored, pending = upload(alice, 1), upload(alice, 2, anchor=False)
    bobs_robot, _ = robot_create(owner=bob, name="bobs")
    _token, _key = make_owner_token(alice.owner)
    client = chain_client()
    assert client.has_access(alice.owner.eoa_address, bob.eoa_address)
    assert client.has_access(bob.eoa_address, alice.owner.eoa_address)

    with pytest.raises(WrongPassword):
        account_delete(owner=alice.owner, password="not the password")
    alice.owner.refresh_from_db()
    assert alice.owner.deleted_at is None
    assert alice.owner.user.is_active
    assert_live(anchored)

    with django_capture_on_commit_callbacks(execute=True):
        account_delete(owner=alice.owner, password=TEST_PASSWORD)

    owner = alice.owner
    owner.refresh_from_db()
    assert owner.deleted_at is not None
    # Records: all deleted, anchored or not, and their ciphertext gone.
    for record in (anchored, pending):
        assert_purged(record, reason=Record.Deletion.ACCOUNT)
    # Grants given and received: revoked in the portal and on chain.
    assert set(Grant.objects.values_list("status", flat=True)) == {Grant.Status.REVOKED}
    assert not client.has_access(owner.eoa_address, bob.eoa_address)
    assert not client.has_access(bob.eoa_address, owner.eoa_address)
    # Credentials: no sign-in, no token, no robot; bob's robot untouched.
    assert not owner.user.check_password(TEST_PASSWORD)
    assert not owner.user.has_usable_password()
    assert not owner.user.is_active
    assert not OwnerToken.objects.filter(owner=owner, revoked_at__isnull=True).exists()
    assert not Robot.objects.filter(owner=owner, is_active=True).exists()
    assert Robot.objects.get(pk=bobs_robot.pk).is_active
    assert AccountEvent.objects.filter(owner=owner, kind=AccountEvent.Kind.ACCOUNT_DELETED).exists()
    # The username cannot be taken over, nor the account be granted to.
    with pytest.raises(UsernameTaken):
        owner_create(username=owner.username, password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    for identifier in (owner.username, owner.eoa_address):
        with pytest.raises(OwnerNotFound):
            owner_resolve(identifier)
    # Bob's own records are bob's: nothing of his was deleted.
    assert not Record.objects.filter(owner=bob, deleted_at__isnull=False).exists()


def _crash_between_tombstone_and_purge(alice: RobotSetup, bob, upload, monkeypatch) -> None:
    """A deletion whose purge never ran (the worker died) is never shown as live, and the
    next run completes it, even after a storage failure."""
    crashed = upload(alice, 4)
    # No on-commit: the purge queued after the deletion never runs, as if the worker died.
    done = records_delete(owner=alice.owner, actor=alice.owner.user, record_ids=[crashed.pk])
    assert done.deleted == 1
    crashed = fresh(crashed)
    assert crashed.is_deleted
    assert crashed.purged_at is None
    assert stored(crashed)  # still stored, but never shown as live:
    for viewer in (alice.owner, bob):
        with pytest.raises(RecordDeleted) as refused:
            record_open(record_id=crashed.id, viewer=viewer)
        assert f"deleted on {crashed.deleted_at:%Y-%m-%d}" in str(refused.value)
        assert f"by {alice.owner.username}" in str(refused.value)
    # The worker's check says "deleted", never TAMPERED, and raises no alarm.
    verdict = records_verify(record_ids=[crashed.id], viewer_id=bob.pk)[0].verdict
    assert verdict.outcome == Verdict.Outcome.DELETED
    # The storage fails once (an S3 server away): the record stays to purge.
    storage_class = type(envelope_storage())
    real_delete = storage_class.delete

    def unavailable(self: object, name: str) -> None:
        raise OSError("storage unavailable")

    monkeypatch.setattr(storage_class, "delete", unavailable)
    assert records_purge() == 0
    assert fresh(crashed).purged_at is None
    monkeypatch.setattr(storage_class, "delete", real_delete)
    assert retention_apply()["purged"] == 1
    assert_purged(crashed, reason=Record.Deletion.OWNER)
    assert retention_apply()["purged"] == 0
    assert fresh(crashed).tampered_at is None
