"""Scoped and expiring grants: enforced in every list and at every view (content, proof,
record detail), held on chain as a scope commitment and an expiry that the check at view
compares with the portal's."""

from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from accounts.services.robots import robot_create
from chainworker import services as chain_services
from chainworker.models import Deployment
from sharing.grant_terms import grant_terms_make
from sharing.models import Grant, Record, Verdict
from sharing.scope import scope_commitment
from sharing.selectors.grants import grant_count_received, owners_granting
from sharing.selectors.records import record_list_shared_with, record_list_visible_to
from sharing.services.grants import grant_create, grant_revoke, grant_terms_change
from sharing.verification.check import records_verify
from tests.api.conftest import RECORDS, session_client
from tests.support.anvil_rpc import chain_time_travel
from tests.support.robot_setup import RobotSetup

pytestmark = pytest.mark.django_db

ODOM, CAMERA = "/robot/odom", "/robot/camera"
DAY = datetime(2026, 1, 1, tzinfo=UTC)


def _at(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


@pytest.fixture
def scoped(make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    """alice with two robots and four anchored records, and bob with a grant to those of
    her first robot on /robot/odom captured on 2026-01-01, expiring in a day."""
    alice = make_robot("alice")
    robot2, token2 = robot_create(owner=alice.owner, name="second")
    other = RobotSetup(alice.owner, alice.key, robot2, token2)
    # One anchoring run for all four (the last upload's): one tree, one transaction.
    records = {
        "inside": upload(alice, 1, topic=ODOM, time=_at(DAY + timedelta(hours=10)), anchor=False),
        "other_topic": upload(
            alice, 2, topic=CAMERA, time=_at(DAY + timedelta(hours=10)), anchor=False
        ),
        "before_window": upload(
            alice, 3, topic=ODOM, time=_at(DAY - timedelta(hours=1)), anchor=False
        ),
        "other_robot": upload(other, 1, topic=ODOM, time=_at(DAY + timedelta(hours=10))),
    }
    for record in records.values():
        record.refresh_from_db()
        assert record.status == Record.Status.ANCHORED
    bob = make_owner("bob")
    terms = grant_terms_make(
        owner=alice.owner,
        robots=[alice.robot.pk],
        topics=[ODOM],
        since=DAY,
        until=DAY + timedelta(days=1),
        expires_at=timezone.now() + timedelta(days=1),
    )
    with django_capture_on_commit_callbacks(execute=True):
        grant = grant_create(owner=alice.owner, grantee=bob, terms=terms)
    grant.refresh_from_db()
    assert grant.status == Grant.Status.ACTIVE
    return alice, bob, grant, records


def _outcome(record, viewer) -> str:
    return records_verify(record_ids=[record.pk], viewer_id=viewer.pk)[0].verdict.outcome


def test_scope_is_on_chain_and_enforced_everywhere(scoped, deployed, client):
    alice, bob, grant, records = scoped
    inside = records["inside"]
    outside = [records[name] for name in ("other_topic", "before_window", "other_robot")]

    # The chain holds the scope's commitment and the expiry, from authorityGrantScoped.
    on_chain = deployed.grant_of(alice.owner.eoa_address, bob.eoa_address)
    assert on_chain.live
    assert on_chain.scope == scope_commitment(grant.scope) != b"\0" * 32
    assert on_chain.expiry == grant.expiry == int(grant.expires_at.timestamp())

    # Lists: only the record inside the scope; the owner still sees all of hers.
    assert list(record_list_visible_to(bob)) == [inside]
    assert list(record_list_shared_with(bob)) == [inside]
    assert record_list_visible_to(alice.owner).count() == 4
    assert list(owners_granting(bob)) == [alice.owner]
    assert grant_count_received(bob) == 1
    api = session_client(bob)
    listed = api.get(RECORDS).json()["results"]
    assert [row["id"] for row in listed] == [str(inside.pk)]
    client.force_login(bob.user)
    shared_page = client.get(reverse("shared")).content.decode()
    assert str(inside.pk) in shared_page
    assert not any(str(record.pk) in shared_page for record in outside)

    # Views: the check at view lets the record inside through, and refuses the others.
    assert _outcome(inside, bob) == Verdict.Outcome.VERIFIED
    assert client.get(reverse("record-detail", args=[inside.pk])).status_code == 200
    assert api.get(f"{RECORDS}{inside.pk}/content/").status_code == 200
    assert api.get(f"{RECORDS}{inside.pk}/proof/").status_code == 200
    assert api.get(f"{RECORDS}{inside.pk}/").status_code == 200
    for record in outside:
        assert _outcome(record, bob) == Verdict.Outcome.NO_ACCESS
        assert client.get(reverse("record-detail", args=[record.pk])).status_code == 404
        for suffix in ("content/", "proof/", ""):
            answer = api.get(f"{RECORDS}{record.pk}/{suffix}")
            assert answer.status_code == 404, (suffix, answer.content)
            assert answer.json()["error"] == "not_found"

    # --- the terms in the database and on chain must agree ---------------------------------
    # A row changed behind the portal's back: wider in the database than the commitment on
    # chain, so nothing of it holds; nor does an expiry removed in the database only.
    Grant.objects.filter(pk=grant.pk).update(scope_topics=[ODOM, CAMERA])
    assert _outcome(records["other_topic"], bob) == Verdict.Outcome.NO_ACCESS
    assert _outcome(inside, bob) == Verdict.Outcome.NO_ACCESS
    Grant.objects.filter(pk=grant.pk).update(scope_topics=[ODOM], expires_at=None)
    assert _outcome(inside, bob) == Verdict.Outcome.NO_ACCESS
    Grant.objects.filter(pk=grant.pk).update(expires_at=grant.expires_at)
    assert _outcome(inside, bob) == Verdict.Outcome.VERIFIED

    # Expired in the portal: listed nowhere, refused, and shown as expired on both sides.
    Grant.objects.filter(pk=grant.pk).update(expires_at=timezone.now() - timedelta(seconds=1))
    assert not record_list_shared_with(bob).exists()
    assert grant_count_received(bob) == 0
    assert _outcome(inside, bob) == Verdict.Outcome.NO_ACCESS
    for viewer, row in ((alice.owner, "grant-given-row"), (bob, "grant-received-row")):
        client.force_login(viewer.user)
        html = client.get(reverse("grants")).content.decode()
        assert f'data-shown-status="expired" data-testid="{row}"' in html
        assert ">expired</span>" in html
    Grant.objects.filter(pk=grant.pk).update(expires_at=grant.expires_at)

    # Expired on chain (its clock passed the expiry) while the row says active, unexpired.
    chain_time_travel(deployed.url, grant.expiry + 1)
    grant.refresh_from_db()
    assert grant.status == Grant.Status.ACTIVE
    assert not grant.is_expired
    assert not deployed.grant_of(alice.owner.eoa_address, bob.eoa_address).live
    assert _outcome(inside, bob) == Verdict.Outcome.NO_ACCESS


def test_changing_terms_is_a_new_transaction_and_revoke_still_works(
    scoped, deployed, django_capture_on_commit_callbacks
):
    alice, bob, grant, records = scoped
    wider = grant_terms_make(owner=alice.owner, topics=[ODOM, CAMERA])
    with django_capture_on_commit_callbacks(execute=True) as callbacks:
        changed = grant_terms_change(owner=alice.owner, grantee=bob, terms=wider)
        assert changed.status == Grant.Status.PENDING
        # Pending: nothing of it is read until the chain holds the new terms.
        assert not record_list_shared_with(bob).exists()
    assert callbacks
    changed.refresh_from_db()
    assert changed.status == Grant.Status.ACTIVE
    assert changed.grant_tx != grant.grant_tx
    on_chain = deployed.grant_of(alice.owner.eoa_address, bob.eoa_address)
    assert (on_chain.scope, on_chain.expiry) == (scope_commitment(changed.scope), 0)
    assert _outcome(records["other_topic"], bob) == Verdict.Outcome.VERIFIED
    assert _outcome(records["other_robot"], bob) == Verdict.Outcome.VERIFIED
    assert record_list_shared_with(bob).count() == 4

    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=alice.owner, grantee=bob)
    assert not deployed.grant_of(alice.owner.eoa_address, bob.eoa_address).live
    assert _outcome(records["inside"], bob) == Verdict.Outcome.NO_ACCESS
    assert not record_list_shared_with(bob).exists()


def test_an_outdated_contract_on_a_development_chain_is_deployed_again(scoped, deployed, reconcile):
    """`make run` keeps anvil's state: a contract built from an older contracts/AuthROS.sol
    (before scoped grants) is deployed again and everything re-created from the database."""
    alice, bob, grant, records = scoped
    old_address = deployed.address
    Deployment.objects.filter(is_active=True).update(source_keccak="0x" + "ab" * 32)
    chain_services.chain_identity_forget()
    assert chain_services.chain_identity().state == chain_services.IDENTITY_RESET

    counts = reconcile()

    assert counts["identity"] == chain_services.IDENTITY_RESET
    active = Deployment.objects.get(is_active=True)
    assert active.address != old_address
    assert active.source_keccak == deployed.artifact.source_keccak
    client = chain_services.chain_client()
    assert client.address == active.address
    grant.refresh_from_db()
    assert grant.status == Grant.Status.ACTIVE
    on_chain = client.grant_of(alice.owner.eoa_address, bob.eoa_address)
    assert (on_chain.live, on_chain.scope) == (True, scope_commitment(grant.scope))
    assert _outcome(records["inside"], bob) == Verdict.Outcome.VERIFIED
    assert _outcome(records["other_topic"], bob) == Verdict.Outcome.NO_ACCESS
