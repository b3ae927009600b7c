"""Reading content: only after a `verified` verdict, re-sealed under the reader's own key."""

import pytest

from accounts.selectors import owner_key_bytes, owner_key_current
from core.redis_client import get_redis
from sharing import errors
from sharing.cache import _key as cache_key
from sharing.models import Access, Verdict
from sharing.selectors.records import record_get_visible, record_list_visible_to
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create
from sharing.verification import check
from sharing.verification.opening import record_open, record_reseal_for, records_open
from smcrypto import CryptoError, envelope, sm3

pytestmark = pytest.mark.django_db


@pytest.fixture
def shared(make_robot, make_owner, django_capture_on_commit_callbacks):
    alice = make_robot("alice")
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create(robot=alice.robot, data=alice.seal(1, plaintext=b'{"K": "odom"}'))
    return alice, bob, record


def test_owner_opens_own_record(shared):
    alice, _bob, record = shared
    opened = record_open(record_id=record.pk, viewer=alice.owner)
    assert opened.plaintext == b'{"K": "odom"}'
    assert opened.verdict.outcome == "verified"
    assert opened.header["seq"] == 1


def test_grantee_gets_it_resealed_under_own_key(shared, django_capture_on_commit_callbacks):
    alice, bob, record = shared
    with pytest.raises(errors.AccessDenied):
        record_open(record_id=record.pk, viewer=bob)
    assert record_get_visible(bob, record.pk) is None
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    assert list(record_list_visible_to(bob)) == [record]
    opened = record_open(record_id=record.pk, viewer=bob)
    resealed = record_reseal_for(opened=opened, viewer=bob)
    header, plaintext = envelope.open(owner_key_bytes(owner_key_current(bob)), resealed)
    assert plaintext == b'{"K": "odom"}'
    assert header == opened.header
    with pytest.raises(CryptoError):
        envelope.open(alice.key, resealed)
    grant_revoke(owner=alice.owner, grantee=bob)
    with pytest.raises(errors.AccessDenied):
        record_open(record_id=record.pk, viewer=bob)
    assert list(record_list_visible_to(bob)) == []


def test_tampered_content_is_never_decrypted(shared):
    alice, _bob, record = shared
    cached = bytearray(get_redis().get(cache_key(record.pk)))
    cached[-3] ^= 0x10
    get_redis().set(cache_key(record.pk), bytes(cached))
    with pytest.raises(errors.IntegrityCheckFailed) as refused:
        record_open(record_id=record.pk, viewer=alice.owner)
    assert refused.value.http_status == 409


def test_unknown_record(shared):
    alice, _bob, _record = shared
    with pytest.raises(errors.RecordNotFound):
        record_open(record_id="not-a-uuid", viewer=alice.owner)
    assert record_get_visible(alice.owner, "not-a-uuid") is None


def test_opening_many_gives_each_record_its_own_outcome(
    shared, make_robot, django_capture_on_commit_callbacks
):
    alice, bob, anchored = shared
    with django_capture_on_commit_callbacks(execute=True):
        tampered = record_create(robot=alice.robot, data=alice.seal(2))
    pending = record_create(robot=alice.robot, data=alice.seal(3))  # anchoring not run
    cached = bytearray(get_redis().get(cache_key(tampered.pk)))
    cached[-1] ^= 1
    get_redis().set(cache_key(tampered.pk), bytes(cached))

    opened, not_yet, refused = records_open(
        records=[anchored, pending, tampered],
        viewer=alice.owner,
        kind=Access.Kind.PAGE,
        credential="session",
    )
    assert opened.plaintext == b'{"K": "odom"}'
    assert isinstance(not_yet, errors.NotAnchoredYet)
    assert isinstance(refused, errors.IntegrityCheckFailed)
    # Someone without a grant gets a refusal for each, and nothing else.
    assert all(
        isinstance(result, errors.AccessDenied)
        for result in records_open(
            records=[anchored, tampered], viewer=bob, kind="page", credential="session"
        )
    )


def test_a_view_fetches_and_hashes_the_envelope_once(shared, monkeypatch):
    """The worker fetches and hashes; the view decrypts the bytes the worker checked."""
    alice, _bob, record = shared
    fetches, hashes = [], []
    real_fetch, real_hash = check.envelopes_fetch, sm3.sm3_hex

    def counting_fetch(records):
        fetches.extend(record.pk for record in records)
        return real_fetch(records)

    def counting_hash(data):
        hashes.append(len(data))
        return real_hash(data)

    monkeypatch.setattr(check, "envelopes_fetch", counting_fetch)
    monkeypatch.setattr(sm3, "sm3_hex", counting_hash)
    opened = record_open(record_id=record.pk, viewer=alice.owner)
    assert opened.plaintext == b'{"K": "odom"}'
    assert fetches == [record.pk]
    assert hashes == [record.size]
    assert sm3.sm3_hex(opened.envelope) == opened.verdict.chain_digest


def test_the_view_decrypts_what_the_worker_checked_not_a_later_copy(shared, monkeypatch):
    """Stored bytes that change after the check are never what is shown."""
    alice, _bob, record = shared
    checked = get_redis().get(cache_key(record.pk))
    real_verify = check.records_verify

    def verify_then_tamper(**kwargs):
        result = real_verify(**kwargs)
        changed = bytearray(checked)
        changed[-1] ^= 1
        get_redis().set(cache_key(record.pk), bytes(changed))
        return result

    monkeypatch.setattr(check, "records_verify", verify_then_tamper)
    opened = record_open(record_id=record.pk, viewer=alice.owner)
    assert opened.envelope == checked
    assert opened.plaintext == b'{"K": "odom"}'


@pytest.mark.parametrize("outcome", ["no_access", "tampered", "not_anchored_yet"])
def test_a_refusal_carries_its_record_and_verdict(shared, outcome):
    alice, bob, record = shared
    viewer = alice.owner
    if outcome == "no_access":
        viewer = bob
    elif outcome == "tampered":
        cached = bytearray(get_redis().get(cache_key(record.pk)))
        cached[-1] ^= 1
        get_redis().set(cache_key(record.pk), bytes(cached))
    else:
        record = record_create(robot=alice.robot, data=alice.seal(2))  # anchoring not run
    with pytest.raises(errors.ViewRefused) as refused:
        record_open(record_id=record.pk, viewer=viewer)
    assert refused.value.record.pk == record.pk
    assert refused.value.record.owner.username == "alice"
    assert refused.value.verdict.outcome == outcome
    assert Verdict.objects.get(pk=refused.value.verdict.pk).access.viewer_id == viewer.pk
