"""Grants (by username or address, revocation) and the audit trail read from the chain."""

import re
import uuid

import pytest
from django.test import Client
from django.urls import reverse

from chainworker.chain import ChainEvent, record_id_to_bytes32
from sharing.audit import audit_entries_from_events
from sharing.models import Grant, Record
from sharing.services import record_create_batch
from stack.anvil import free_port

pytestmark = pytest.mark.django_db


def test_grant_by_username_then_revoke(client, make_owner, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    client.force_login(alice.user)
    assert client.get(reverse("grants")).status_code == 200
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(reverse("grants"), {"grantee": "bob"})
    assert page.status_code == 302
    grant = Grant.objects.get(owner=alice, grantee=bob)
    assert grant.status == Grant.Status.ACTIVE
    html = client.get(reverse("grants")).content.decode()
    # The grant is pending until the chain confirms it, and the message says so.
    assert "bob may read your records once it is confirmed" in html
    assert "may now read" not in html
    assert grant.grant_tx in html
    assert re.search(r'data-grantee="bob" data-status="active"', html)

    client.force_login(bob.user)
    received = client.get(reverse("grants")).content.decode()
    assert re.search(r'data-owner="alice" data-status="active"', received)
    assert grant.grant_tx in received

    client.force_login(alice.user)
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(reverse("grant-revoke"), {"grantee": "bob"})
    assert page.status_code == 302
    grant.refresh_from_db()
    assert grant.status == Grant.Status.REVOKED
    html = client.get(reverse("grants")).content.decode()
    assert "bob can no longer read your records" in html
    assert grant.revoke_tx in html
    assert re.search(r'data-grantee="bob" data-status="revoked"', html)

    again = client.post(reverse("grant-revoke"), {"grantee": "bob"}, follow=True)
    assert "has no access to revoke" in again.content.decode()
    assert client.get(reverse("grant-revoke")).status_code == 405


def test_grant_by_eoa_address(client, make_owner, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    client.force_login(alice.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": bob.eoa_address.lower()})
    assert Grant.objects.get(owner=alice, grantee=bob).status == Grant.Status.ACTIVE


def test_grant_refusals_change_nothing(client, make_owner, pending_owner):
    alice = make_owner("alice")
    make_owner("bob")
    pending_owner("newbie")
    client.force_login(alice.user)
    client.post(reverse("grants"), {"grantee": "bob"})
    for grantee, message in [
        ("", "This field is required"),
        ("nobody", "no owner &#x27;nobody&#x27;"),
        ("0x" + "00" * 20, "no owner"),
        ("alice", "always reads its own records"),
        ("newbie", "is not registered on chain yet"),
        ("bob", "already has access"),
    ]:
        page = client.post(reverse("grants"), {"grantee": grantee})
        assert page.status_code == 400, grantee
        assert message in page.content.decode(), grantee
    assert Grant.objects.count() == 1


def test_grant_forms_need_csrf(make_owner):
    alice, _bob = make_owner("alice"), make_owner("bob")
    client = Client(enforce_csrf_checks=True)
    client.force_login(alice.user)
    assert client.post(reverse("grants"), {"grantee": "bob"}).status_code == 403
    assert client.post(reverse("grant-revoke"), {"grantee": "bob"}).status_code == 403
    assert client.post(reverse("logout")).status_code == 403
    assert not Grant.objects.exists()


def test_audit_shows_the_owners_history_from_the_chain(
    client, make_robot, make_owner, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    make_owner("bob")
    carol = make_robot("carol")
    first, second = upload(alice, 1), upload(alice, 2)
    upload(carol, 1)  # someone else's upload is not in alice's trail
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "bob"})
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grant-revoke"), {"grantee": "bob"})
    client.force_login(carol.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "alice"})

    client.force_login(alice.owner.user)
    page = client.get(reverse("audit"))
    html = page.content.decode()
    assert page.status_code == 200
    kinds = re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)
    # newest first
    assert kinds == [
        "grant-received",
        "revoke-given",
        "grant-given",
        "upload",
        "upload",
        "Registered",
        "Enrolled",
    ]
    owner = alice.owner
    assert owner.register_tx in html
    assert owner.enroll_tx in html
    assert "Granted access to bob" in html
    assert "Revoked access to bob" in html
    assert "carol granted you access" in html
    for record in (first, second):
        assert record.tx_hash in html
        assert reverse("record-detail", args=[record.id]) in html
    assert f"Block {owner.registered_block}" in html
    assert carol.owner.register_tx not in html


def test_audit_groups_a_batch_and_caps_its_list(
    client, make_robot, monkeypatch, django_capture_on_commit_callbacks
):
    monkeypatch.setattr("sharing.audit.AUDIT_RECORDS_PER_UPLOAD", 2)
    alice = make_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(
            robot=alice.robot, envelopes=[alice.seal(seq) for seq in (1, 2, 3)]
        )
    tx_hashes = {record.tx_hash for record in Record.objects.filter(owner=alice.owner)}
    assert len(tx_hashes) == 1
    client.force_login(alice.owner.user)
    html = client.get(reverse("audit")).content.decode()
    assert "Anchored 3 records" in html
    assert "and 1 more" in html
    assert tx_hashes.pop() in html
    assert str(records[0].id) in html


def test_audit_without_the_chain(client, pending_owner, settings):
    owner = pending_owner()
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    client.force_login(owner.user)
    page = client.get(reverse("audit"))
    assert page.status_code == 503
    assert "cannot be read right now" in page.content.decode()


def test_audit_entries_decode_name_and_group_the_events(pending_owner, monkeypatch):
    monkeypatch.setattr("sharing.audit.AUDIT_RECORDS_PER_UPLOAD", 2)
    alice, bob = pending_owner("alice"), pending_owner("bob")
    stranger = "0x" + "ab" * 20
    ids = [uuid.uuid4() for _ in range(4)]

    def event(name: str, block: int, tx: str, **args: object) -> ChainEvent:
        return ChainEvent(name, args, block, tx, 0)

    events = [
        event("Enrolled", 1, "0x01", eoa=alice.eoa_address),
        event("Registered", 2, "0x02", eoa=alice.eoa_address, commitment=b"\x11" * 32),
        *(
            event("DataUploaded", 3, "0x03", owner=alice.eoa_address, id=record_id_to_bytes32(i))
            for i in ids[:3]
        ),
        event("DataUploaded", 4, "0x04", owner=alice.eoa_address, id=record_id_to_bytes32(ids[3])),
        event("AuthorityGranted", 5, "0x05", owner=alice.eoa_address, grantee=bob.eoa_address),
        event("AuthorityRevoked", 6, "0x06", owner=stranger, grantee=alice.eoa_address.lower()),
    ]
    entries = audit_entries_from_events(alice, events)

    assert [(e.kind, e.block_number) for e in entries] == [
        ("revoke-received", 6),
        ("grant-given", 5),
        ("upload", 4),
        ("upload", 3),
        ("Registered", 2),
        ("Enrolled", 1),
    ]
    revoked, granted, single, batch, registered, _ = entries
    assert revoked.title == f"{stranger} revoked your access"
    assert granted.title == "Granted access to bob"
    assert (single.title, [i for i, _ in single.records]) == ("Anchored 1 record", [str(ids[3])])
    assert batch.title == "Anchored 3 records"
    assert [i for i, _ in batch.records] == [str(i) for i in ids[:2]]
    assert batch.more_records == 1
    # Ids the portal has no record of (here: none uploaded) are listed without a link.
    assert all(record is None for _, record in batch.records)
    assert registered.detail == "0x" + "11" * 32
