"""The admin console: every model listed without secrets, the actions, the chain status page."""

import pytest
from django.contrib.auth import get_user_model
from django.urls import reverse

from accounts.models import AccountEvent, OwnerKey, Robot
from sharing.models import Credential, Record, SecurityEvent, Verdict
from sharing.selectors.access import verdict_latest
from stack.anvil import free_port
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

MODELS = [
    "accounts_owner",
    "accounts_ownerkey",
    "accounts_robot",
    "accounts_accountevent",
    "sharing_record",
    "sharing_grant",
    "sharing_verdict",
    "sharing_securityevent",
    "chainworker_deployment",
    "auth_user",
    "accounts_robotpairing",
    "accounts_ownertoken",
    "accounts_eoafunding",
    "accounts_secretfingerprint",
    "accounts_chainactivity",
    "sharing_anchorroot",
    "sharing_grantchange",
    "sharing_access",
    "sharing_export",
    "sharing_exportrecord",
    "alerts_alertpreferences",
    "alerts_webhookendpoint",
    "alerts_alert",
    "alerts_alertdelivery",
    "alerts_alertcondition",
    "chainworker_operatoralert",
]


@pytest.fixture
def admin_client(client, db):
    user = get_user_model().objects.create_superuser("root", password=TEST_PASSWORD)
    client.force_login(user)
    return client


@pytest.fixture
def populated(make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    from sharing.services.grants import grant_create
    from sharing.verification.opening import record_open

    alice = make_robot("alice")
    bob = make_owner("bob")
    record = upload(alice, 1)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    record_open(record_id=record.id, viewer=bob)
    return alice, bob, record


def test_every_model_is_listed_searchable_and_never_shows_secrets(admin_client, populated):
    alice, _bob, record = populated
    key = OwnerKey.objects.get(owner=alice.owner)
    secrets = [
        alice.token,
        alice.robot.token_hash,
        alice.key.hex(),
        bytes(key.key_wrapped).hex(),
        bytes(alice.owner.eoa_key_wrapped).hex(),
    ]
    index = admin_client.get(reverse("admin:index")).content.decode()
    assert reverse("admin:chain-status") in index
    for model in MODELS:
        listing = admin_client.get(reverse(f"admin:{model}_changelist"), {"q": "alice"})
        assert listing.status_code == 200, model
        html = listing.content.decode()
        assert not any(secret in html for secret in secrets), model
    for obj, model in [
        (alice.owner, "accounts_owner"),
        (key, "accounts_ownerkey"),
        (alice.robot, "accounts_robot"),
        (record, "sharing_record"),
        (Verdict.objects.first(), "sharing_verdict"),
    ]:
        page = admin_client.get(reverse(f"admin:{model}_change", args=[obj.pk]))
        assert page.status_code == 200, model
        html = page.content.decode()
        assert not any(secret in html for secret in secrets), model
        assert "key_wrapped" not in html
        assert "token_hash" not in html
    # Rows come from the services, not from forms here.
    assert admin_client.get(reverse("admin:accounts_owner_add")).status_code == 403
    assert admin_client.get(reverse("admin:sharing_record_add")).status_code == 403


@pytest.mark.usefixtures("records_mode")  # one failed record beside an anchored one
def test_reanchor_failed_records(
    admin_client, make_robot, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    failed = upload(alice, 1, anchor=False)
    anchored = upload(alice, 2)
    Record.objects.filter(pk=failed.pk).update(
        status=Record.Status.FAILED, anchor_attempts=20, failure_reason="not anchored"
    )
    with django_capture_on_commit_callbacks(execute=True):
        page = admin_client.post(
            reverse("admin:sharing_record_changelist"),
            {"action": "reanchor_failed", "_selected_action": [str(failed.pk), str(anchored.pk)]},
            follow=True,
        )
    assert "1 failed record(s) are pending again" in page.content.decode()
    assert "1 selected record(s) had not failed" in page.content.decode()
    failed.refresh_from_db()
    assert failed.status == Record.Status.ANCHORED
    assert failed.anchor_attempts == 1
    assert failed.failure_reason == ""
    # The owner sees the operator's repair, naming only the record that had failed.
    event = AccountEvent.objects.get(owner=alice.owner)
    assert event.kind == AccountEvent.Kind.ADMIN_ACTION
    assert event.actor.username == "root"
    assert event.detail == {"action": "re-anchored failed records", "records": [str(failed.pk)]}


def test_reverify_records(admin_client, make_robot, upload):
    alice = make_robot("alice")
    good = upload(alice, 1)
    bad = upload(alice, 2)
    pending = upload(alice, 3, anchor=False)
    tamper(bad)
    page = admin_client.post(
        reverse("admin:sharing_record_changelist"),
        {"action": "reverify", "_selected_action": [str(r.pk) for r in (good, bad, pending)]},
        follow=True,
    )
    html = page.content.decode()
    assert "1 verified" in html
    assert "1 TAMPERED" in html
    assert "1 not anchored yet" in html
    assert f"TAMPERED: {bad.pk}" in html
    assert SecurityEvent.objects.filter(record=bad).exists()
    verdict = Verdict.objects.get(record=good, access__viewer=alice.owner, outcome="verified")
    # The operator's check, not the owner viewing their own data.
    assert str(verdict.access.checked_by.pk) == admin_client.session["_auth_user_id"]
    assert verdict.access.checked_by.is_staff
    assert verdict.access.credential == Credential.OPERATOR
    assert "checked by operator" in str(verdict)
    assert verdict_latest(good, alice.owner) is None
    event = AccountEvent.objects.get(owner=alice.owner)
    assert (event.kind, event.actor.username) == (AccountEvent.Kind.ADMIN_ACTION, "root")
    assert event.detail["action"] == "re-verified records against the chain"
    assert sorted(event.detail["records"]) == sorted(str(r.pk) for r in (good, bad, pending))


def test_revoke_robot_tokens_from_the_admin(admin_client, make_robot):
    alice = make_robot("alice")
    admin_client.post(
        reverse("admin:accounts_robot_changelist"),
        {"action": "revoke_tokens", "_selected_action": [str(alice.robot.pk)]},
    )
    assert not Robot.objects.get(pk=alice.robot.pk).is_active
    event = AccountEvent.objects.get(owner=alice.owner)
    assert (event.kind, event.actor.username) == (AccountEvent.Kind.ROBOT_TOKEN_REVOKED, "root")
    assert event.detail["robot_id"] == str(alice.robot.pk)


def test_chain_status_page(admin_client, make_robot, upload, deployed):
    alice = make_robot("alice")
    upload(alice, 1, anchor=False)
    page = admin_client.get(reverse("admin:chain-status"))
    html = page.content.decode()
    assert page.status_code == 200
    assert f'data-testid="chain-id">{deployed.chain_id}<' in html
    assert f'data-testid="contract-address">{deployed.address}<' in html
    assert 'data-testid="latest-block">' in html
    assert " ETH<" in html
    assert '?status__exact=pending">1</a>' in html
    assert "message" in html  # the Celery queue's length, read from Redis


def test_chain_status_page_when_the_chain_is_down(admin_client, settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    page = admin_client.get(reverse("admin:chain-status"))
    assert page.status_code == 503
    assert "not reachable" in page.content.decode()


def test_chain_status_needs_staff(client, pending_owner):
    client.force_login(pending_owner().user)
    page = client.get(reverse("admin:chain-status"))
    assert page.status_code == 302
    assert page["Location"].startswith(reverse("admin:login"))
