"""Grants on chain, and the integrity check every view goes through."""

from datetime import UTC, datetime, timedelta

import pytest
from django.utils import timezone

from core.redis_client import get_redis
from sharing import errors
from sharing.cache import _key as cache_key
from sharing.cache import envelope_cache_get
from sharing.models import Grant, Record, SecurityEvent, Verdict
from sharing.selectors.grants import owner_resolve
from sharing.services.anchoring import records_anchor
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create
from sharing.storage import envelope_storage
from sharing.verification.check import records_verify
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db


@pytest.fixture
def anchored(make_robot, django_capture_on_commit_callbacks):
    """An owner with a robot and one anchored record."""
    setup = make_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create(robot=setup.robot, data=setup.seal(1))
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    return setup, record


def _grant(owner, grantee, capture):
    with capture(execute=True):
        grant = grant_create(owner=owner, grantee=grantee)
    grant.refresh_from_db()
    return grant


def _revoke(owner, grantee, capture):
    with capture(execute=True):
        grant = grant_revoke(owner=owner, grantee=grantee)
    grant.refresh_from_db()
    return grant


def test_grant_and_revoke_reach_the_chain(make_owner, deployed, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    grant = _grant(alice, bob, django_capture_on_commit_callbacks)
    assert grant.status == Grant.Status.ACTIVE
    assert grant.grant_tx.startswith("0x")
    assert deployed.has_access(alice.eoa_address, bob.eoa_address)
    revoked = _revoke(alice, bob, django_capture_on_commit_callbacks)
    assert revoked.status == Grant.Status.REVOKED
    assert revoked.revoke_tx.startswith("0x")
    assert not deployed.has_access(alice.eoa_address, bob.eoa_address)
    regranted = _grant(alice, bob, django_capture_on_commit_callbacks)
    assert regranted.pk != grant.pk
    assert regranted.status == Grant.Status.ACTIVE


def test_grant_refusals(make_owner, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    with pytest.raises(errors.SelfGrant):
        grant_create(owner=alice, grantee=alice)
    with pytest.raises(errors.NoGrant):
        grant_revoke(owner=alice, grantee=bob)
    _grant(alice, bob, django_capture_on_commit_callbacks)
    with pytest.raises(errors.AlreadyGranted):
        grant_create(owner=alice, grantee=bob)
    carol = make_owner("carol")
    carol.chain_state = "pending"
    carol.save()
    with pytest.raises(errors.GranteeNotRegistered):
        grant_create(owner=alice, grantee=carol)
    with pytest.raises(errors.NotRegisteredYet):
        grant_create(owner=carol, grantee=alice)
    assert Grant.objects.count() == 1


def test_giving_access_again_after_a_grant_expired_says_to_renew_it(
    make_owner, django_capture_on_commit_callbacks
):
    alice, bob = make_owner("alice"), make_owner("bob")
    grant = _grant(alice, bob, django_capture_on_commit_callbacks)
    Grant.objects.filter(pk=grant.pk).update(expires_at=datetime(2026, 3, 1, 12, 30, tzinfo=UTC))
    with pytest.raises(errors.AlreadyGranted) as refused:
        grant_create(owner=alice, grantee=bob)
    assert str(refused.value) == (
        "Your grant to bob expired at 2026-03-01 12:30 UTC. To give access again, change that "
        "grant: a new expiry, or none."
    )
    # Not expired yet: the plain refusal.
    Grant.objects.filter(pk=grant.pk).update(expires_at=timezone.now() + timedelta(days=1))
    with pytest.raises(errors.AlreadyGranted, match="bob already has access"):
        grant_create(owner=alice, grantee=bob)
    assert Grant.objects.count() == 1


def test_giving_access_again_while_the_revocation_is_on_its_way_says_so(
    make_owner, django_capture_on_commit_callbacks
):
    """A grant being revoked gives nothing: not "already has access", and no second grant."""
    alice, bob = make_owner("alice"), make_owner("bob")
    grant = _grant(alice, bob, django_capture_on_commit_callbacks)
    Grant.objects.filter(pk=grant.pk).update(status=Grant.Status.REVOKING)
    with pytest.raises(errors.RevocationPending) as refused:
        grant_create(owner=alice, grantee=bob)
    assert str(refused.value) == (
        "bob no longer has access, but the revocation is still on its way to the chain. Give "
        "access again once it is confirmed, in a few seconds."
    )
    assert (refused.value.code, refused.value.http_status) == ("revocation_pending", 409)
    assert list(Grant.objects.values_list("status", flat=True)) == [Grant.Status.REVOKING]


def test_grantee_by_username_or_address(make_owner):
    alice = make_owner("alice")
    assert owner_resolve("alice") == alice
    assert owner_resolve(alice.eoa_address.lower()) == alice
    with pytest.raises(errors.OwnerNotFound):
        owner_resolve("nobody")


def test_owner_view_is_verified_and_audited(anchored):
    setup, record = anchored
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    verdict = verification.verdict
    assert verdict.outcome == Verdict.Outcome.VERIFIED
    assert verdict.computed_digest == record.digest == verdict.chain_digest
    assert verdict.block_number >= record.block_number
    assert verdict.source == "cache"
    with envelope_storage().open(record.storage_name, "rb") as handle:
        assert verification.envelope == handle.read()


def test_cache_miss_reads_storage_and_rewarms(anchored, settings):
    setup, record = anchored
    # What a FLUSHDB would do to this test, leaving other runs sharing the Redis alone.
    redis = get_redis()
    redis.delete(*redis.scan_iter(f"{settings.REDIS_KEY_PREFIX}:*"))
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.VERIFIED
    assert verification.verdict.source == "storage"
    assert envelope_cache_get(record.id) == verification.envelope


def test_grantee_sees_until_revoked(anchored, make_owner, django_capture_on_commit_callbacks):
    setup, record = anchored
    bob = make_owner("bob")
    assert (
        records_verify(record_ids=[record.id], viewer_id=bob.pk)[0].verdict.outcome == "no_access"
    )
    _grant(setup.owner, bob, django_capture_on_commit_callbacks)
    assert records_verify(record_ids=[record.id], viewer_id=bob.pk)[0].verdict.outcome == "verified"
    # Revoked in the portal: refused at the next view, before the chain has confirmed it.
    grant_revoke(owner=setup.owner, grantee=bob)
    refused = records_verify(record_ids=[record.id], viewer_id=bob.pk)[0]
    assert refused.verdict.outcome == "no_access"
    assert refused.envelope is None
    assert Verdict.objects.filter(access__viewer=bob).count() == 3


def test_grant_only_in_the_portal_is_not_enough(anchored, make_owner):
    """A portal row without the chain's agreement (e.g. a forged row) grants nothing."""
    setup, record = anchored
    bob = make_owner("bob")
    Grant.objects.create(owner=setup.owner, grantee=bob, status=Grant.Status.ACTIVE)
    assert (
        records_verify(record_ids=[record.id], viewer_id=bob.pk)[0].verdict.outcome == "no_access"
    )


def test_changed_cache_is_tampered(anchored):
    setup, record = anchored
    cached = bytearray(envelope_cache_get(record.id))
    cached[-5] ^= 0xFF
    get_redis().set(cache_key(record.id), bytes(cached))
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.TAMPERED
    assert verification.verdict.source == "cache"
    assert verification.envelope is None
    record.refresh_from_db()
    assert record.tampered_at is not None
    event = SecurityEvent.objects.get(kind=SecurityEvent.Kind.TAMPERED_ON_VIEW)
    assert event.record_id == record.id
    # The bad cached copy is dropped; durable storage still holds the anchored bytes.
    assert envelope_cache_get(record.id) is None
    assert (
        records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict.outcome
        == "verified"
    )


def test_changed_durable_copy_is_tampered(anchored):
    setup, record = anchored
    tamper(record)
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.TAMPERED
    assert verification.verdict.source == "storage"
    assert verification.envelope is None
    again = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert again.verdict.outcome == Verdict.Outcome.TAMPERED


def test_not_anchored_yet(make_robot, deployed):
    setup = make_robot()
    record = record_create(robot=setup.robot, data=setup.seal(1))  # on-commit work not run
    verification = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert verification.verdict.outcome == Verdict.Outcome.NOT_ANCHORED_YET
    assert verification.envelope is None


@pytest.mark.usefixtures("records_mode")
def test_anchoring_is_idempotent(make_robot, deployed):
    setup = make_robot()
    records = [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in range(1, 6)]
    # A previous attempt anchored two of them and died before writing it down.
    from accounts.selectors import owner_eoa_account
    from sharing.services.anchoring import anchor_item

    account = owner_eoa_account(setup.owner)
    deployed.data_upload_batch(account, [anchor_item(r) for r in records[:2]])
    Record.objects.filter(pk__in=[r.pk for r in records[:2]]).update(anchor_attempts=1)
    assert records_anchor(owner_id=setup.owner.pk) == 3
    assert set(Record.objects.values_list("status", flat=True)) == {"anchored"}
    uploads = deployed.events(names=["DataUploaded"])
    assert len(uploads) == 5
    settled = Record.objects.get(pk=records[0].pk)
    assert settled.block_number == uploads[0].block_number
    assert records_anchor(owner_id=setup.owner.pk) == 0


@pytest.mark.usefixtures("records_mode")
def test_taken_id_without_a_recorded_attempt_is_settled(make_robot, deployed):
    setup = make_robot()
    records = [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in range(1, 4)]
    from accounts.selectors import owner_eoa_account
    from sharing.services.anchoring import anchor_item

    deployed.data_upload(owner_eoa_account(setup.owner), anchor_item(records[1]))
    records_anchor(owner_id=setup.owner.pk)
    assert Record.objects.filter(status="anchored").count() == 3
    assert len(deployed.events(names=["DataUploaded"])) == 3


@pytest.mark.usefixtures("records_mode")
def test_other_digest_on_chain_fails_the_record_and_raises_an_alarm(make_robot, deployed):
    setup = make_robot()
    record = record_create(robot=setup.robot, data=setup.seal(1))
    from accounts.selectors import owner_eoa_account
    from sharing.services.anchoring import anchor_item

    wrong = anchor_item(record)
    object.__setattr__(wrong, "digest", bytes(32 - 1) + b"\x01")
    deployed.data_upload(owner_eoa_account(setup.owner), wrong)
    Record.objects.filter(pk=record.pk).update(anchor_attempts=1)
    records_anchor(owner_id=setup.owner.pk)
    record.refresh_from_db()
    assert record.status == Record.Status.FAILED
    assert SecurityEvent.objects.filter(
        kind=SecurityEvent.Kind.CHAIN_DIGEST_MISMATCH, record=record
    ).exists()


def test_a_deleted_envelope_file_is_tampered_not_an_error(anchored, settings):
    setup, record = anchored
    redis = get_redis()
    redis.delete(*redis.scan_iter(f"{settings.REDIS_KEY_PREFIX}:*"))
    envelope_storage().delete(record.storage_name)
    verdict = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict
    assert (verdict.outcome, verdict.source) == (Verdict.Outcome.TAMPERED, "storage")
    assert SecurityEvent.objects.filter(record=record).exists()
