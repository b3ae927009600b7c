"""Gas that never stops the service: on a chain with gas prices (anvil charges a base fee)
the operator tops up an owner's EOA from the funding budget, "cannot pay" waits without using
up attempts, a spent budget raises an operator alert, and the dashboard and the admin warn
before an account runs dry. Nothing is sent on a zero-gas chain.
"""

import re

import pytest
from django.urls import reverse
from eth_account import Account

from accounts.models import ChainState, EoaFunding
from accounts.selectors import owner_eoa_account
from accounts.services.funding import (
    TOPUP_REASON,
    eoa_funding_spent,
    owner_eoa_gas,
    owner_top_up,
    owners_low_on_gas,
)
from accounts.services.keys import key_rotate, sm4_key_generate
from accounts.services.owners import owner_create
from accounts.services.registration import chain_work_sweep
from chainworker import services as chain_services
from chainworker.client import AuthROSChain
from chainworker.errors import InsufficientFunds
from chainworker.models import OperatorAlert
from chainworker.work import WAITING_FOR_GAS
from portal.celery import app as celery_app
from sharing.models import Grant, Record
from sharing.services import anchoring
from sharing.services import sweep as sharing_sweep
from sharing.services.grants import grant_create
from sharing.services.uploads import record_create_batch
from stack.anvil import start_anvil
from tests.support.anchoring_checks import assert_anchored_exactly_once
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup

pytestmark = pytest.mark.django_db


def _empty(client: AuthROSChain, setup: RobotSetup) -> None:
    """Send the owner's ether away with its own key: what is left pays for no batch."""
    account = owner_eoa_account(setup.owner)
    fee = client.fee_per_gas()
    balance = client.balance(account.address)
    client.transfer(account, Account.create().address, balance - 21_000 * fee)
    assert client.balance(account.address) < 50_000 * fee


def _upload(setup: RobotSetup, seqs: range, capture, *, anchor: bool = True) -> list[Record]:
    with capture(execute=anchor):
        return record_create_batch(robot=setup.robot, envelopes=[setup.seal(s) for s in seqs])


def _assert_anchored_once(client: AuthROSChain, records: list[Record]) -> None:
    for record in records:
        record.refresh_from_db()
        assert record.status == Record.Status.ANCHORED
        assert record.failure_reason == ""
        assert record.anchor_attempts == 1  # InsufficientFunds used up none
    assert_anchored_exactly_once(client)


def test_an_account_emptied_mid_run_is_topped_up_and_every_record_anchored(
    make_robot, deployed, settings, django_capture_on_commit_callbacks
):
    assert deployed.fee_per_gas() > 0
    # A task that meets InsufficientFunds is retried, as a worker would (inline here).
    celery_app.conf.task_eager_propagates = False
    alice = make_robot("alice")
    before = _upload(alice, range(1, 4), django_capture_on_commit_callbacks)
    _empty(deployed, alice)
    # Each upload's anchoring meets InsufficientFunds first, or finds the account topped up.
    later = []
    for start in (4, 9, 14):
        later += _upload(alice, range(start, start + 5), django_capture_on_commit_callbacks)
    _assert_anchored_once(deployed, before + later)
    assert not Record.objects.exclude(status=Record.Status.ANCHORED).exists()
    top_up = EoaFunding.objects.get(owner=alice.owner, reason=TOPUP_REASON)
    assert top_up.tx_hash
    assert deployed.w3.eth.get_transaction(top_up.tx_hash)["to"] == alice.owner.eoa_address
    assert EoaFunding.objects.filter(owner=alice.owner).count() == 2  # registration, top-up
    assert not owner_eoa_gas(owner=alice.owner).low
    assert not OperatorAlert.objects.exists()


def test_with_the_budget_spent_records_wait_and_the_operator_is_alerted(
    make_robot, deployed, settings, django_capture_on_commit_callbacks, client
):
    settings.ANCHOR_MAX_ATTEMPTS = 2
    settings.ANCHOR_STALE_AFTER = 0
    bob = make_robot("bob")
    settings.SIGNUP_FUNDING_BUDGET_WEI = eoa_funding_spent()  # no wei left for a top-up
    _empty(deployed, bob)
    records = _upload(bob, range(1, 6), django_capture_on_commit_callbacks, anchor=False)
    for _ in range(settings.ANCHOR_MAX_ATTEMPTS + 2):  # more runs than attempts allowed
        with pytest.raises(InsufficientFunds):
            anchoring.records_anchor(owner_id=bob.owner.pk)
    for record in records:
        record.refresh_from_db()
        assert record.status == Record.Status.PENDING
        assert record.failure_reason == WAITING_FOR_GAS
        assert record.anchor_attempts == 0
    alert = OperatorAlert.objects.get()
    assert alert.kind == OperatorAlert.Kind.FUNDING_BUDGET_SPENT
    assert alert.resolved_at is None
    assert not EoaFunding.objects.filter(reason=TOPUP_REASON).exists()
    # The owner's record page says why the record waits.
    client.force_login(bob.owner.user)
    page = client.get(f"/records/{records[0].pk}/")
    assert page.status_code == 409
    assert 'data-testid="pending-reason"' in page.content.decode()
    assert "waiting for gas" in page.content.decode()

    # The operator raises the budget; the sweep tops the account up. The run that met "cannot
    # pay" waits for its retry, which anchors what waited (the anchoring sweep queues no run of
    # its own meanwhile: that one is queued).
    settings.SIGNUP_FUNDING_BUDGET_WEI = 50 * 10**18
    assert chain_work_sweep()["top_ups"] == 1
    with django_capture_on_commit_callbacks(execute=True):
        sharing_sweep.chain_work_sweep()
    assert Record.objects.filter(owner=bob.owner, status=Record.Status.PENDING).count() == 5
    assert anchoring.records_anchor(owner_id=bob.owner.pk) == 5  # the retry
    _assert_anchored_once(deployed, records)
    alert.refresh_from_db()
    assert alert.resolved_at is not None
    assert not OperatorAlert.objects.filter(resolved_at=None).exists()
    assert EoaFunding.objects.filter(owner=bob.owner, reason="top-up").count() == 1


def test_an_owner_above_the_threshold_is_not_topped_up(make_owner, deployed, settings):
    settings.CHAIN_EOA_FUNDING_GAS = 20_000_000
    settings.CHAIN_EOA_TOPUP_BELOW_GAS = 2_000_000
    owner = make_owner("cid")
    assert owner_top_up(owner_id=owner.pk) is None
    assert chain_work_sweep()["top_ups"] == 0
    assert EoaFunding.objects.filter(owner=owner).count() == 1  # registration only


def test_the_operator_unable_to_pay_is_an_alert(make_robot, deployed, settings, operator):
    dan = make_robot("dan")
    _empty(deployed, dan)
    settings.CHAIN_DEV_FAUCET = False  # a real network: nobody refills the operator
    fee = deployed.fee_per_gas()
    deployed.transfer(
        operator,
        Account.create().address,
        deployed.balance(operator.address) - 21_000 * fee,
    )
    with pytest.raises(InsufficientFunds):
        owner_top_up(owner_id=dan.owner.pk)
    alert = OperatorAlert.objects.get(resolved_at=None)
    assert (alert.kind, alert.subject) == (OperatorAlert.Kind.OPERATOR_CANNOT_PAY, operator.address)
    # The sweep sees the operator low too (one alert each), and funding it resolves both; the
    # top-up it queues fails again meanwhile and is retried, as a worker would.
    celery_app.conf.task_eager_propagates = False
    settings.CHAIN_OPERATOR_LOW_WEI = 10**18
    chain_work_sweep()
    kinds = set(OperatorAlert.objects.filter(resolved_at=None).values_list("kind", flat=True))
    assert kinds == {
        OperatorAlert.Kind.OPERATOR_CANNOT_PAY,
        OperatorAlert.Kind.OPERATOR_LOW_BALANCE,
    }
    deployed.dev_faucet(operator.address, 10 * 10**18)
    assert owner_top_up(owner_id=dan.owner.pk) is not None
    chain_work_sweep()
    assert not OperatorAlert.objects.filter(resolved_at=None).exists()
    assert OperatorAlert.objects.count() == 2


def test_the_dashboard_warns_before_the_account_runs_dry(client, make_owner, deployed, settings):
    owner = make_owner("eve")
    client.force_login(owner.user)
    html = client.get(reverse("dashboard")).content.decode()
    assert 'data-testid="gas-low"' not in html
    assert "tops your account up when it holds less than" in html
    # Its balance falls under the threshold: the owner is told before anything waits.
    settings.CHAIN_EOA_TOPUP_BELOW_GAS = 10**9
    html = client.get(reverse("dashboard")).content.decode()
    assert re.search(r'data-testid="gas-low">Your account is low on gas', html)


def test_the_admin_lists_low_accounts_alerts_and_a_low_operator(
    admin_client, make_owner, deployed, settings
):
    frank, gina = make_owner("frank"), make_owner("gina")
    _empty(deployed, RobotSetup(frank, b"", None, ""))
    chain_services.operator_alert_raise(
        kind=OperatorAlert.Kind.FUNDING_BUDGET_SPENT, subject="eoa-funding-budget"
    )
    page = admin_client.get(reverse("admin:chain-status"))
    assert page.status_code == 200
    html = page.content.decode()
    low = re.findall(r'<tr data-testid="low-balance"><td>([^<]+)</td>', html)
    assert low == ["frank"]
    assert gina.eoa_address not in html
    assert html.count('data-testid="operator-alert"') == 1
    assert "funding-budget-spent" in html
    assert 'data-testid="operator-low"' not in html
    settings.CHAIN_OPERATOR_LOW_WEI = 10**30
    assert (
        'data-testid="operator-low"'
        in admin_client.get(reverse("admin:chain-status")).content.decode()
    )
    # The alerts' own list is read-only.
    listing = admin_client.get(reverse("admin:chainworker_operatoralert_changelist"))
    assert listing.status_code == 200
    assert "eoa-funding-budget" in listing.content.decode()
    assert admin_client.get(reverse("admin:chainworker_operatoralert_add")).status_code == 403


def test_one_open_alert_per_kind_and_subject(db):
    first = chain_services.operator_alert_raise(kind="k", subject="s", detail={"n": 1})
    again = chain_services.operator_alert_raise(kind="k", subject="s", detail={"n": 2})
    assert again.pk == first.pk
    assert again.detail == {"n": 2}
    assert chain_services.operator_alert_resolve(kind="k", subject="s")
    assert not chain_services.operator_alert_resolve(kind="k", subject="s")
    reopened = chain_services.operator_alert_raise(kind="k", subject="s")
    assert reopened.pk != first.pk
    assert OperatorAlert.objects.filter(resolved_at=None).count() == 1


@pytest.mark.process
def test_a_zero_gas_chain_needs_no_top_up(settings, django_capture_on_commit_callbacks, client):
    with start_anvil(zero_gas=True) as node:  # as `make run` starts it
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()
        try:
            chain_services.contract_deploy()
            with django_capture_on_commit_callbacks(execute=True):
                owner = owner_create(
                    username="hana", password=TEST_PASSWORD, sm4_key=sm4_key_generate()
                )
            assert chain_services.chain_client().balance(owner.eoa_address) == 0
            assert owner_top_up(owner_id=owner.pk) is None
            assert chain_work_sweep()["top_ups"] == 0
            assert owners_low_on_gas() == []
            assert not EoaFunding.objects.exists()
            settings.CHAIN_OPERATOR_LOW_WEI = 10**30  # no gas to pay: never "low"
            assert not chain_services.operator_balance_check().low
            assert not OperatorAlert.objects.exists()
            client.force_login(owner.user)
            html = client.get(reverse("dashboard")).content.decode()
            assert "This chain charges nothing for gas" in html
            assert 'data-testid="gas-low"' not in html
        finally:
            chain_services._clients.clear()


def test_grants_and_key_rotations_wait_for_gas_and_go_through(
    make_owner, deployed, django_capture_on_commit_callbacks
):
    celery_app.conf.task_eager_propagates = False  # retried as a worker would
    ivy, jack = make_owner("ivy"), make_owner("jack")
    _empty(deployed, RobotSetup(ivy, b"", None, ""))
    with django_capture_on_commit_callbacks(execute=True):
        grant = grant_create(owner=ivy, grantee=jack)
    grant.refresh_from_db()
    assert grant.status == Grant.Status.ACTIVE
    assert grant.failure_reason == ""
    assert deployed.has_access(ivy.eoa_address, jack.eoa_address)
    assert EoaFunding.objects.filter(owner=ivy, reason="top-up").count() == 1

    _empty(deployed, RobotSetup(ivy, b"", None, ""))
    with django_capture_on_commit_callbacks(execute=True):
        key = key_rotate(owner=ivy, sm4_key=sm4_key_generate())
    key.refresh_from_db()
    assert key.chain_state == ChainState.CONFIRMED
    assert deployed.commitment_of(ivy.eoa_address).hex() == key.commitment.removeprefix("0x")
    assert EoaFunding.objects.filter(owner=ivy, reason="top-up").count() == 2
