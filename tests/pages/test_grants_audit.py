"""Grants (by username or address, revocation) and the audit trail (tests/sharing/
test_audit_index.py has the index it reads)."""

import re
from datetime import timedelta

import pytest
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from accounts.services.robots import robot_token_revoke
from chainworker.services import chain_client
from sharing.models import Grant, Record
from sharing.services.uploads import record_create_batch

pytestmark = pytest.mark.django_db


def test_grant_by_username_then_revoke(client, make_owner, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    client.force_login(alice.user)
    assert client.get(reverse("grants")).status_code == 200
    # Nothing ticked: all records, no expiry. A page says so and asks; nothing is granted yet.
    with django_capture_on_commit_callbacks(execute=True):
        asked = client.post(reverse("grants"), {"grantee": "bob"})
    assert asked.status_code == 200
    html = asked.content.decode()
    assert 'data-testid="grant-confirm-all"' in html
    assert "every record of every robot of yours" in html
    assert "until you revoke it" in html
    assert 'name="confirm_all" value="True"' in html
    assert not Grant.objects.exists()
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    assert page.status_code == 302
    grant = Grant.objects.get(owner=alice, grantee=bob)
    assert grant.status == Grant.Status.ACTIVE
    # The page says what the grant is as it shows its row: confirmed already (issue 48).
    html = client.get(page.url).content.decode()
    assert "The grant to bob is confirmed on chain: bob may read what it covers." in html
    assert "being written" not in html
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


def test_the_grant_notice_says_what_its_row_says(client, make_owner):
    """A grant the chain has not confirmed yet is said to be on its way, beside its row
    "pending"; one confirmed, beside "active" (issue 48)."""
    alice, bob = make_owner("alice"), make_owner("bob")
    client.force_login(alice.user)
    page = client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    assert page.url == reverse("grants") + "?made=bob"
    html = client.get(page.url).content.decode()
    assert re.search(r'data-grantee="bob" data-status="pending"', html)
    assert "The grant to bob is being written to the chain" in html
    assert "once its row below says active" in html
    Grant.objects.filter(owner=alice, grantee=bob).update(status=Grant.Status.ACTIVE)
    html = client.get(page.url).content.decode()
    assert "The grant to bob is confirmed on chain" in html
    # Nothing said of a grant there is not, or of a name nobody has.
    for made in ("carol", "", "\x00", "x" * 500):
        html = client.get(reverse("grants"), {"made": made}).content.decode()
        assert 'data-testid="grant-made"' not in html


def test_grant_by_eoa_address(client, make_owner, django_capture_on_commit_callbacks):
    alice, bob = make_owner("alice"), make_owner("bob")
    client.force_login(alice.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": bob.eoa_address.lower(), "confirm_all": "True"})
    assert Grant.objects.get(owner=alice, grantee=bob).status == Grant.Status.ACTIVE


def test_grant_refusals_change_nothing(client, make_owner, pending_owner):
    alice = make_owner("alice")
    make_owner("bob")
    pending_owner("newbie")
    client.force_login(alice.user)
    client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    for grantee, message in [
        ("", "Enter the username or address of the owner to share with."),
        ("nobody", "There is no owner with the username or address “nobody”: check the spelling"),
        ("0x" + "00" * 20, "There is no owner with the username or address"),
        ("alice", "You always see your own records: name another owner."),
        ("newbie", "newbie&#x27;s account is not registered on the chain yet: try again"),
        ("bob", "bob already has access. To change which records they may read"),
    ]:
        page = client.post(reverse("grants"), {"grantee": grantee, "confirm_all": "True"})
        assert page.status_code == 400, grantee
        assert message in page.content.decode(), grantee
    assert Grant.objects.count() == 1


def test_grant_forms_need_csrf(make_owner):
    alice, _bob = make_owner("alice"), make_owner("bob")
    client = Client(enforce_csrf_checks=True)
    client.force_login(alice.user)
    assert (
        client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"}).status_code == 403
    )
    assert client.post(reverse("grant-revoke"), {"grantee": "bob"}).status_code == 403
    assert client.post(reverse("logout")).status_code == 403
    assert not Grant.objects.exists()


def test_audit_shows_the_owners_history(
    client, make_robot, make_owner, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    make_owner("bob")
    carol = make_robot("carol")
    first, second = upload(alice, 1), upload(alice, 2)
    upload(carol, 1)  # someone else's upload is not in alice's trail
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grant-revoke"), {"grantee": "bob"})
    client.force_login(carol.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "alice", "confirm_all": "True"})

    client.force_login(alice.owner.user)
    page = client.get(reverse("audit"))
    html = page.content.decode()
    assert page.status_code == 200
    kinds = re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)
    # newest first
    # Grants, revocations and keys on top, then the anchoring, a minute a line.
    assert kinds[:5] == ["grant-received", "revoke-given", "grant-given", "registered", "enrolled"]
    assert kinds[-1] == "upload"
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


def test_audit_lists_robot_key_registrations_and_revocations_from_their_events(
    client, make_owner, pair_robot, on_commit
):
    owner = make_owner("alice")
    robot = pair_robot(owner).robot
    on_commit(lambda: robot_token_revoke(robot=robot, actor=owner.user))
    robot.refresh_from_db()
    added, revoked = chain_client().events(names=["RobotKeyAdded", "RobotKeyRevoked"])
    client.force_login(owner.user)
    html = client.get(reverse("audit")).content.decode()
    kinds = re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)
    assert kinds[:3] == ["robot-key-revoked", "robot-key-added", "registered"]
    assert f"Registered the signing key of robot {robot.name}" in html
    assert f"Revoked the signing key of robot {robot.name}" in html
    assert f"key hash {robot.key_hash}" in html
    for event in (added, revoked):
        assert event.tx_hash in html
        assert f"Block {event.block_number}" in html
    # Their kind is one of the filter's.
    html = client.get(reverse("audit"), {"kind": "robot_key_added"}).content.decode()
    kinds = re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)
    assert kinds == ["robot-key-added"]
    times = re.findall(r'data-testid="audit-time">([^<]+)<', html)
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", t) for t in times)


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


def test_a_limited_grant_needs_no_confirmation_and_a_change_to_everything_does(
    client, make_robot, make_owner, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    make_owner("bob")
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(reverse("grants"), {"grantee": "bob", "topics": ["/robot/odom"]})
    assert page.status_code == 302
    grant = Grant.objects.get()
    assert grant.scope_topics == ["/robot/odom"]
    # Changing the terms to nothing chosen asks too, and changes nothing until confirmed.
    asked = client.post(reverse("grants"), {"grantee": "bob", "change": "True"})
    assert asked.status_code == 200
    assert 'data-testid="grant-confirm-all"' in asked.content.decode()
    assert 'name="change" value="True"' in asked.content.decode()
    grant.refresh_from_db()
    assert grant.scope_topics == ["/robot/odom"]
    with django_capture_on_commit_callbacks(execute=True):
        done = client.post(
            reverse("grants"), {"grantee": "bob", "change": "True", "confirm_all": "True"}
        )
    assert done.status_code == 302
    grant = Grant.objects.filter(status__in=Grant.LIVE).get()
    assert grant.scope_topics == []


def test_an_expired_grant_offers_remove_not_revoke(client, make_owner):
    alice = make_owner("alice")
    make_owner("bob")
    client.force_login(alice.user)
    client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    expired = timezone.now().replace(microsecond=0) - timedelta(days=1)
    Grant.objects.filter(owner=alice).update(status=Grant.Status.ACTIVE, expires_at=expired)
    html = client.get(reverse("grants")).content.decode()
    assert 'data-testid="remove-grant"' in html
    assert "Remove the expired grant to bob" in html
    assert 'data-testid="revoke-grant"' not in html
    confirm = client.get(reverse("grant-revoke-confirm"), {"grantee": "bob"}).content.decode()
    assert "Remove the expired grant to bob?" in confirm
    assert f"It expired on {expired:%Y-%m-%d %H:%M:%S} UTC" in confirm
    assert "Revoke access" not in confirm
