"""F3: sign-up cannot drain the operator. Registrations are throttled per client address and
overall (through the register page), each new EOA gets only the gas it needs (nothing on a
zero-gas chain) within a funding budget per period, and an operator may have to approve each
sign-up before any chain work is done.
"""

import logging
from datetime import timedelta

import pytest
from django.contrib.auth import get_user_model
from django.test import Client
from django.urls import reverse
from django.utils import timezone

from accounts.models import AccountEvent, Approval, ChainState, EoaFunding, Owner
from accounts.services.funding import FUNDING_BUDGET_SPENT, eoa_funding_amount
from accounts.services.keys import sm4_key_generate
from accounts.services.owners import owner_create
from accounts.services.registration import chain_work_sweep
from accounts.tasks import owner_register
from chainworker import services as chain_services
from stack.anvil import start_anvil
from tests.pages.conftest import encrypted_key
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


def _register(address: str, username: str, **headers: str) -> object:
    """POST the register page as a new browser at `address` would (its script's ciphertext)."""
    client = Client(REMOTE_ADDR=address, **headers)
    form = {
        "username": username,
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(sm4_key_generate()),
    }
    return client.post(reverse("register"), form)


# --- throttles ----------------------------------------------------------------------------


def test_registrations_are_limited_per_client_address(settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "2/hour"
    settings.SIGNUP_RATE_TOTAL = "100/hour"
    assert _register("203.0.113.7", "ann").status_code == 302
    assert _register("203.0.113.7", "ben").status_code == 302
    # A client naming another address itself is still counted by its peer address.
    refused = _register("203.0.113.7", "cid", HTTP_X_FORWARDED_FOR="198.51.100.1")
    assert refused.status_code == 429
    assert int(refused["Retry-After"]) > 0
    html = refused.content.decode()
    assert 'data-testid="signup-throttled"' in html
    assert "Try again in 60 minutes" in html
    assert not Owner.objects.filter(user__username="cid").exists()
    assert not get_user_model().objects.filter(username="cid").exists()
    # Another address is not held back by the first one's registrations.
    assert _register("203.0.113.8", "cid").status_code == 302
    assert Owner.objects.count() == 3


def test_registrations_are_limited_overall(settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "100/hour"
    settings.SIGNUP_RATE_TOTAL = "3/hour"
    for number in range(3):
        assert _register(f"203.0.113.{number}", f"user{number}").status_code == 302
    refused = _register("203.0.113.200", "late")
    assert refused.status_code == 429
    assert Owner.objects.count() == 3


def test_only_registrations_that_create_an_owner_count(settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "1/hour"
    client = Client(REMOTE_ADDR="203.0.113.9")
    word_key = {"key_ciphertext": encrypted_key(b"mysecretpassword")}
    form = {"username": "dan", "password1": TEST_PASSWORD, "password2": TEST_PASSWORD}
    # An invalid form, and a form the service refuses (a weak key): nothing made, not counted.
    assert client.post(reverse("register"), {**form, "password2": "other"}).status_code == 400
    assert client.post(reverse("register"), {**form, **word_key}).status_code == 400
    assert _register("203.0.113.9", "dan").status_code == 302
    assert _register("203.0.113.9", "eve").status_code == 429


def test_the_limits_are_shared_by_every_web_process(settings, redis_client):
    """Counted in Redis: what one process counted, another sees (a new client, no cache)."""
    settings.SIGNUP_RATE_PER_ADDRESS = "1/hour"
    assert _register("203.0.113.10", "fay").status_code == 302
    keys = list(redis_client.scan_iter(f"{settings.REDIS_KEY_PREFIX}:{{signup}}:*"))
    assert len(keys) == 2  # this address's window and the overall one
    assert _register("203.0.113.10", "gus").status_code == 429


# --- funding only for the gas needed, within a budget -------------------------------------


def test_the_funding_is_the_gas_needed_at_the_current_fee_capped(settings):
    settings.CHAIN_EOA_FUNDING_GAS = 20_000_000
    settings.CHAIN_EOA_FUNDING_WEI = 10**18
    assert eoa_funding_amount(fee_per_gas=0) == 0
    assert eoa_funding_amount(fee_per_gas=3 * 10**9) == 20_000_000 * 3 * 10**9
    assert eoa_funding_amount(fee_per_gas=10**12) == 10**18


def test_a_new_eoa_gets_the_gas_it_needs_and_the_transfer_is_recorded(
    make_owner, deployed, settings
):
    settings.CHAIN_EOA_FUNDING_GAS = 2_000_000
    assert deployed.fee_per_gas() > 0  # anvil has a base fee (1 gwei)
    owner = make_owner("hal")
    funding = EoaFunding.objects.get(owner=owner)
    assert funding.tx_hash == owner.fund_tx
    sent = deployed.w3.eth.get_transaction(owner.fund_tx)["value"]
    assert sent == funding.amount_wei
    # 2,000,000 gas units at the fee of the moment: far less than the 1 ETH sent before.
    assert sent % 2_000_000 == 0
    assert 0 < sent < settings.CHAIN_EOA_FUNDING_WEI // 10


def test_over_the_budget_a_registration_waits_without_using_up_attempts(
    make_owner, deployed, settings, caplog
):
    settings.CHAIN_EOA_FUNDING_WEI = 10**15  # each EOA gets this much (the cap)
    settings.SIGNUP_FUNDING_BUDGET_WEI = 2 * 10**15
    settings.SIGNUP_FUNDING_PERIOD = 3600
    first, second = make_owner("ida"), make_owner("jon")
    assert first.chain_state == second.chain_state == ChainState.CONFIRMED
    # On the service's logger itself: the eager Celery run sets the root logger up again.
    service_logger = logging.getLogger("accounts.services.funding")
    service_logger.addHandler(caplog.handler)
    try:
        third = make_owner("kim")
    finally:
        service_logger.removeHandler(caplog.handler)
    assert third.chain_state == ChainState.PENDING
    assert third.chain_error == FUNDING_BUDGET_SPENT
    assert not third.fund_tx
    assert not third.enroll_tx
    assert deployed.balance(third.eoa_address) == 0
    assert EoaFunding.objects.count() == 2
    assert "EOA funding budget spent" in caplog.text
    # The task finishes (no retry, no error): the owner waits for the sweep.
    result = owner_register.apply(args=(third.pk,))
    assert result.successful()
    assert result.result == ChainState.PENDING

    # Later: the period moves on, and the sweep queues the waiting registration again.
    settings.ANCHOR_STALE_AFTER = 0
    EoaFunding.objects.update(created_at=timezone.now() - timedelta(hours=2))
    assert chain_work_sweep()["registrations"] == 1
    third.refresh_from_db()
    assert third.chain_state == ChainState.CONFIRMED
    assert third.chain_error == ""
    assert EoaFunding.objects.filter(owner=third, tx_hash=third.fund_tx).exists()


@pytest.mark.process
def test_a_zero_gas_chain_sends_no_ether(settings, django_capture_on_commit_callbacks):
    with start_anvil(zero_gas=True) as node:  # as `make run` starts it
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()
        chain_services.contract_deploy()
        client = chain_services.chain_client()
        assert client.fee_per_gas() == 0
        with django_capture_on_commit_callbacks(execute=True):
            owner = owner_create(username="lea", password=TEST_PASSWORD, sm4_key=sm4_key_generate())
        owner.refresh_from_db()
        assert owner.chain_state == ChainState.CONFIRMED
        assert owner.fund_tx == ""
        assert client.balance(owner.eoa_address) == 0
        assert not EoaFunding.objects.exists()
        assert client.is_registered(owner.eoa_address)
        chain_services._clients.clear()


# --- operator approval --------------------------------------------------------------------


def test_with_approval_on_a_sign_up_does_nothing_on_chain_until_approved(
    deployed, settings, admin_client, django_capture_on_commit_callbacks
):
    settings.SIGNUP_APPROVAL = True
    settings.ANCHOR_STALE_AFTER = 0
    browser = Client()
    form = {
        "username": "max",
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(sm4_key_generate()),
    }
    with django_capture_on_commit_callbacks(execute=True):
        assert browser.post(reverse("register"), form).status_code == 302
    owner = Owner.objects.get(user__username="max")
    assert owner.approval == Approval.AWAITING
    assert owner.chain_state == ChainState.PENDING
    assert (owner.fund_tx, owner.enroll_tx, owner.register_tx) == ("", "", "")
    assert not deployed.is_enrolled(owner.eoa_address)
    page = browser.get(reverse("registration-progress")).content.decode()
    assert "awaits an operator's approval" in page
    assert 'data-state="awaiting"' in page
    assert chain_work_sweep()["registrations"] == 0

    with django_capture_on_commit_callbacks(execute=True):
        answer = admin_client.post(
            reverse("admin:accounts_owner_changelist"),
            {"action": "approve_signups", "_selected_action": [str(owner.pk)]},
        )
    assert answer.status_code == 302
    owner.refresh_from_db()
    assert owner.approval == Approval.APPROVED
    assert owner.approved_by.username == "admin"
    assert owner.approved_at is not None
    assert owner.chain_state == ChainState.CONFIRMED
    assert deployed.is_registered(owner.eoa_address)
    event = AccountEvent.objects.get(owner=owner, kind=AccountEvent.Kind.SIGNUP_APPROVED)
    assert event.actor.username == "admin"
    assert "registered on chain" in browser.get(reverse("registration-progress")).content.decode()


def test_a_refused_sign_up_is_deactivated_and_never_reaches_the_chain(
    deployed, settings, admin_client, django_capture_on_commit_callbacks
):
    settings.SIGNUP_APPROVAL = True
    settings.ANCHOR_STALE_AFTER = 0
    browser = Client()
    form = {
        "username": "ned",
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(sm4_key_generate()),
    }
    with django_capture_on_commit_callbacks(execute=True):
        browser.post(reverse("register"), form)
        admin_client.post(
            reverse("admin:accounts_owner_changelist"),
            {"action": "refuse_signups", "_selected_action": [str(Owner.objects.get().pk)]},
        )
    owner = Owner.objects.select_related("user").get()
    assert owner.approval == Approval.REFUSED
    assert not owner.user.is_active
    assert AccountEvent.objects.filter(owner=owner, kind=AccountEvent.Kind.SIGNUP_REFUSED).exists()
    # Its session stops working, and nothing queues it again.
    assert browser.get(reverse("dashboard")).status_code == 302
    assert chain_work_sweep()["registrations"] == 0
    with django_capture_on_commit_callbacks(execute=True):
        owner_register.apply(args=(owner.pk,))
    owner.refresh_from_db()
    assert owner.chain_state == ChainState.PENDING
    assert not deployed.is_enrolled(owner.eoa_address)
    # Approving it afterwards changes nothing: only sign-ups awaiting approval move.
    admin_client.post(
        reverse("admin:accounts_owner_changelist"),
        {"action": "approve_signups", "_selected_action": [str(owner.pk)]},
    )
    owner.refresh_from_db()
    assert owner.approval == Approval.REFUSED


def test_an_operator_made_owner_needs_no_approval(make_owner, settings):
    settings.SIGNUP_APPROVAL = True
    owner = make_owner("ola")  # the service, as `manage.py owner_create` calls it
    assert owner.approval == Approval.APPROVED
    assert owner.chain_state == ChainState.CONFIRMED
