"""Reconciliation: a chain that lost blocks, or was reset, is brought back to what the database
says, by the periodic job (sharing.services.reconcile.chain_reconcile) or `manage.py chain_resync`.

"Lost blocks" are the test node's snapshots reverted (`blocks_lost`); a "reset" points
CHAIN_RPC_URL at a new node (`fresh_chain`).
"""

from collections import Counter

import pytest
from django.core.management import call_command

from accounts.models import ChainState, OwnerKey
from accounts.selectors import owner_eoa_account
from accounts.services.keys import key_rotate
from chainworker import services as chain_services
from chainworker.codec import AnchorItem, bytes32_to_record_id
from sharing.models import Grant, Record, SecurityEvent, Verdict
from sharing.services.grants import grant_create, grant_revoke
from sharing.verification.check import records_verify
from smcrypto import sm4

# Records mode: what the chain holds per record id. Roots: tests/sharing/services/test_roots.py.
pytestmark = [pytest.mark.django_db, pytest.mark.usefixtures("records_mode")]


def _uploaded_ids(client) -> Counter:
    return Counter(
        bytes32_to_record_id(event.args["id"]) for event in client.events(names=["DataUploaded"])
    )


def test_a_record_the_chain_lost_is_anchored_again_and_verifies(
    make_robot, upload, deployed, reconcile, blocks_lost
):
    setup = make_robot("alice")
    with blocks_lost():
        record = upload(setup, 1)
        assert record.status == Record.Status.ANCHORED
    # The node lost the block with the record.
    lost = records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0]
    assert lost.verdict.outcome == Verdict.Outcome.NOT_ANCHORED_YET

    counts = reconcile()

    assert counts["records_lost"] == 1
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    client = chain_services.chain_client()
    assert (
        client.data_query(record.id, owner=record.owner.eoa_address).digest.hex() == record.digest
    )
    assert records_verify(record_ids=[record.id], viewer_id=setup.owner.pk)[0].verdict.outcome == (
        Verdict.Outcome.VERIFIED
    )
    assert _uploaded_ids(client) == {record.id: 1}


def test_another_digest_on_chain_is_a_security_event(
    make_robot, upload, deployed, reconcile, blocks_lost
):
    setup = make_robot("alice")
    with blocks_lost():
        record = upload(setup, 1)
    # Someone with the owner's EOA put another digest under the record's id.
    deployed.resync_nonce(setup.owner.eoa_address)
    forged = AnchorItem(record.id, b"\x11" * 32, record.captured_at, record.data_type)
    deployed.data_upload(owner_eoa_account(setup.owner), forged)

    counts = reconcile()

    assert counts["digests"] == 1
    record.refresh_from_db()
    assert record.status == Record.Status.FAILED
    event = SecurityEvent.objects.get(record=record)
    assert event.kind == SecurityEvent.Kind.CHAIN_DIGEST_MISMATCH
    assert event.detail["chain"] == "11" * 32


def test_grants_the_chain_lost_are_sent_again(
    make_owner, deployed, reconcile, on_commit, blocks_lost
):
    alice, bob, carol = make_owner("alice"), make_owner("bob"), make_owner("carol")
    on_commit(lambda: grant_create(owner=alice, grantee=carol))
    with blocks_lost():
        granted = on_commit(lambda: grant_create(owner=alice, grantee=bob))
        revoked = on_commit(lambda: grant_revoke(owner=alice, grantee=carol))
    # Bob's grant and carol's revocation are gone.
    assert not deployed.has_access(alice.eoa_address, bob.eoa_address)
    assert deployed.has_access(alice.eoa_address, carol.eoa_address)

    counts = reconcile()

    assert (counts["grants_lost"], counts["revokes_lost"]) == (1, 1)
    granted.refresh_from_db()
    revoked.refresh_from_db()
    assert (granted.status, revoked.status) == (Grant.Status.ACTIVE, Grant.Status.REVOKED)
    client = chain_services.chain_client()
    assert client.has_access(alice.eoa_address, bob.eoa_address)
    assert not client.has_access(alice.eoa_address, carol.eoa_address)


def test_a_lost_registration_and_rotation_are_sent_again(
    make_owner, deployed, reconcile, on_commit, blocks_lost
):
    alice = make_owner("alice")
    with blocks_lost():
        bob = make_owner("bob")
        new_key = on_commit(lambda: key_rotate(owner=alice, sm4_key=sm4.generate_key()))
        new_key.refresh_from_db()
        assert new_key.chain_state == ChainState.CONFIRMED
    # Bob's registration and alice's rotation are gone.

    counts = reconcile()

    assert counts["registrations_lost"] == 1
    assert counts["rotations_lost"] == 1
    client = chain_services.chain_client()
    bob.refresh_from_db()
    assert bob.chain_state == ChainState.CONFIRMED
    assert client.is_registered(bob.eoa_address)
    assert "0x" + client.commitment_of(alice.eoa_address).hex() == new_key.commitment
    assert OwnerKey.objects.get(pk=new_key.pk).chain_state == ChainState.CONFIRMED


def _world(make_robot, make_owner, upload, on_commit):
    """Two owners with records, a rotated key, an active and a revoked grant."""
    alice, bob = make_robot("alice"), make_robot("bob")
    carol = make_owner("carol")
    records = [upload(alice, 1), upload(alice, 2), upload(bob, 1)]
    new_key = sm4.generate_key()
    on_commit(lambda: key_rotate(owner=bob.owner, sm4_key=new_key))
    bob.key = new_key
    records.append(upload(bob, 2))
    on_commit(lambda: grant_create(owner=alice.owner, grantee=bob.owner))
    on_commit(lambda: grant_create(owner=alice.owner, grantee=carol))
    on_commit(lambda: grant_revoke(owner=alice.owner, grantee=carol))
    assert all(r.status == Record.Status.ANCHORED for r in records)
    return [alice.owner, bob.owner, carol], records


def _assert_recreated(owners, records) -> None:
    client = chain_services.chain_client()
    assert client.has_code(client.address)
    for owner in owners:
        owner.refresh_from_db()
        assert owner.chain_state == ChainState.CONFIRMED
        assert client.is_registered(owner.eoa_address)
        newest = owner.keys.order_by("-created_at").first()
        assert "0x" + client.commitment_of(owner.eoa_address).hex() == newest.commitment
    for grant in Grant.objects.all():
        on_chain = client.has_access(grant.owner.eoa_address, grant.grantee.eoa_address)
        assert on_chain == (grant.status == Grant.Status.ACTIVE), grant
    assert Grant.objects.filter(status=Grant.Status.ACTIVE).count() == 1
    uploaded = _uploaded_ids(client)
    assert uploaded == {record.id: 1 for record in records}  # each exactly once
    for record in records:
        record.refresh_from_db()
        assert record.status == Record.Status.ANCHORED
        assert (
            client.data_query(record.id, owner=record.owner.eoa_address).digest.hex()
            == record.digest
        )
        verdict = records_verify(record_ids=[record.id], viewer_id=record.owner_id)[0].verdict
        assert verdict.outcome == Verdict.Outcome.VERIFIED


def test_a_reset_development_chain_is_redeployed_and_recreated(
    make_robot, make_owner, upload, on_commit, fresh_chain, reconcile
):
    owners, records = _world(make_robot, make_owner, upload, on_commit)
    fresh_chain()

    counts = reconcile()

    assert counts["identity"] == "reset"
    assert counts["owners"] == 3
    assert counts["records"] == 4
    _assert_recreated(owners, records)
    # Once re-created, the next run finds nothing to repair.
    again = reconcile()
    assert again["identity"] == "same"
    assert again["records_lost"] == again["registrations_lost"] == again["grants_lost"] == 0


def test_chain_resync_recreates_on_demand(
    make_robot, make_owner, upload, on_commit, fresh_chain, capsys
):
    owners, records = _world(make_robot, make_owner, upload, on_commit)
    fresh_chain()

    on_commit(lambda: call_command("chain_resync", "--yes"))

    out = capsys.readouterr().out
    assert "Deployed AuthROS" in out
    assert "3 owner registration(s), 1 grant(s), 4 record(s)" in out
    _assert_recreated(owners, records)


def test_chain_resync_asks_first(make_robot, upload, monkeypatch):
    setup = make_robot("alice")
    record = upload(setup, 1)
    monkeypatch.setattr("builtins.input", lambda prompt: "n")
    with pytest.raises(Exception, match="cancelled"):
        call_command("chain_resync")
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    setup.owner.refresh_from_db()
    assert setup.owner.chain_state == ChainState.CONFIRMED
