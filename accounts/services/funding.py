"""Ether for owners' EOAs, sent by the operator: funding at registration and top-ups.

Every new account costs the operator gas, so funding is limited by a budget per period
(SIGNUP_FUNDING_BUDGET_WEI, EoaFunding rows) and waits, with an operator alert, once it is
spent. Owners who send transactions are topped up when low (owner_top_up, queued by chain work
that met InsufficientFunds and by the sweep), and the admin's chain status page lists the low.
"""

import logging
from dataclasses import dataclass
from datetime import timedelta

from django.conf import settings
from django.db.models import F, Max, Sum
from django.utils import timezone
from eth_account.signers.local import LocalAccount

from accounts.models import ChainActivity, ChainState, EoaFunding, Owner
from accounts.services.activity import chain_activity_record
from chainworker.client import AuthROSChain
from chainworker.errors import ChainError, InsufficientFunds
from chainworker.gas import LowBalance
from chainworker.models import OperatorAlert
from chainworker.services import (
    chain_client,
    chain_work_check,
    operator_account,
    operator_alert_raise,
    operator_alert_resolve,
    operator_balance_check,
    operator_ensure_funded,
)
from chainworker.work import exclusive
from core.outbox import enqueue

logger = logging.getLogger(__name__)

# What a registration waiting for the funding budget shows its owner (Owner.chain_error).
FUNDING_BUDGET_SPENT = (
    "waiting: the portal has funded as many new accounts as it may for now; registration "
    "continues by itself later"
)
# The subject of the operator alert raised while the funding budget is spent.
FUNDING_BUDGET_SUBJECT = "eoa-funding-budget"


def eoa_funding_amount(*, fee_per_gas: int, gas: int | None = None) -> int:
    """Wei a new EOA is sent: CHAIN_EOA_FUNDING_GAS (or `gas`) gas units at `fee_per_gas` (the
    chain's current max fee per gas), at most CHAIN_EOA_FUNDING_WEI; 0 on a zero-gas chain."""
    units = settings.CHAIN_EOA_FUNDING_GAS if gas is None else gas
    return min(units * max(fee_per_gas, 0), settings.CHAIN_EOA_FUNDING_WEI)


def eoa_funding_spent() -> int:
    """Wei sent (or about to be) to owners' EOAs within the last SIGNUP_FUNDING_PERIOD."""
    since = timezone.now() - timedelta(seconds=settings.SIGNUP_FUNDING_PERIOD)
    total = EoaFunding.objects.filter(created_at__gte=since).aggregate(total=Sum("amount_wei"))
    return int(total["total"] or 0)


def eoa_fund(
    *,
    owner: Owner,
    client: AuthROSChain,
    operator: LocalAccount,
    amount_wei: int,
    reason: str = "registration",
) -> str | None:
    """Send `amount_wei` to the owner's EOA if the period's funding budget allows it, recorded
    in EoaFunding; the transaction hash, or None (nothing sent) when the budget is spent (an
    operator alert says so). Raises InsufficientFunds (and alerts) when the operator cannot pay."""
    # A row of an earlier attempt that did not get its transaction out is reused, not re-counted.
    entry = owner.fundings.filter(tx_hash="").order_by("created_at").first()
    if entry is None:
        # One worker at a time between the sum and the new row, across processes and owners.
        with exclusive("eoa-funding-budget", timeout=30, wait=30):
            spent = eoa_funding_spent()
            budget = settings.SIGNUP_FUNDING_BUDGET_WEI
            if spent + amount_wei > budget:
                logger.warning(
                    "EOA funding budget spent (%s of %s wei in %.0f s): %s of %s waits",
                    spent,
                    budget,
                    settings.SIGNUP_FUNDING_PERIOD,
                    reason,
                    owner,
                )
                if reason == "registration":
                    Owner.objects.filter(pk=owner.pk).update(chain_error=FUNDING_BUDGET_SPENT)
                operator_alert_raise(
                    kind=OperatorAlert.Kind.FUNDING_BUDGET_SPENT,
                    subject=FUNDING_BUDGET_SUBJECT,
                    detail={
                        "spent_wei": str(spent),
                        "budget_wei": str(budget),
                        "period_seconds": settings.SIGNUP_FUNDING_PERIOD,
                        "waiting": f"{reason} of {owner}",
                    },
                )
                return None
            entry = EoaFunding.objects.create(owner=owner, amount_wei=amount_wei, reason=reason)
            operator_alert_resolve(
                kind=OperatorAlert.Kind.FUNDING_BUDGET_SPENT, subject=FUNDING_BUDGET_SUBJECT
            )
    try:
        tx_hash = client.transfer(operator, owner.eoa_address, int(entry.amount_wei)).tx_hash
    except InsufficientFunds:
        operator_alert_raise(
            kind=OperatorAlert.Kind.OPERATOR_CANNOT_PAY,
            subject=operator.address,
            detail={"amount_wei": str(entry.amount_wei), "to": owner.eoa_address},
        )
        raise
    operator_alert_resolve(kind=OperatorAlert.Kind.OPERATOR_CANNOT_PAY, subject=operator.address)
    EoaFunding.objects.filter(pk=entry.pk).update(tx_hash=tx_hash)
    return tx_hash


# EoaFunding.reason of a top-up (registration's is "registration").
TOPUP_REASON = "top-up"
# Owners whose balance one sweep or one admin page reads at most (one node call each).
GAS_SCAN_MAX = 200
# Owners who sent a transaction this recently are the ones the sweep keeps topped up.
GAS_SCAN_ACTIVE = timedelta(hours=1)


@dataclass(frozen=True)
class EoaGas:
    """An owner's EOA balance against the top-up threshold at the chain's current fee."""

    owner: Owner
    balance_wei: int
    fee_per_gas: int

    @property
    def zero_gas(self) -> bool:
        return self.fee_per_gas == 0

    @property
    def low_below_wei(self) -> int:
        """CHAIN_EOA_TOPUP_BELOW_GAS gas units at the current fee; 0 on a zero-gas chain."""
        return settings.CHAIN_EOA_TOPUP_BELOW_GAS * max(self.fee_per_gas, 0)

    @property
    def low(self) -> bool:
        return self.balance_wei < self.low_below_wei


def owner_eoa_gas(*, owner: Owner, client: AuthROSChain | None = None) -> EoaGas:
    """What the owner's EOA holds and whether that is low; raises ChainError if the node is away."""
    client = client or chain_client()
    return EoaGas(owner, client.balance(owner.eoa_address), client.fee_per_gas())


def owners_low_on_gas(*, active_since: timedelta | None = None) -> list[EoaGas]:
    """Registered owners whose EOA is below the top-up threshold (none on a zero-gas chain):
    the GAS_SCAN_MAX most recently active, or only those who sent within `active_since`."""
    client = chain_client()
    fee = client.fee_per_gas()
    if fee == 0:
        return []
    owners = Owner.objects.select_related("user").filter(chain_state=ChainState.CONFIRMED)
    if active_since is not None:
        owners = owners.filter(chain_activity__at__gte=timezone.now() - active_since)
    owners = owners.annotate(last_sent=Max("chain_activity__at")).order_by(
        F("last_sent").desc(nulls_last=True), "-pk"
    )
    gas = (EoaGas(owner, client.balance(owner.eoa_address), fee) for owner in owners[:GAS_SCAN_MAX])
    return [one for one in gas if one.low]


def owner_top_up(*, owner_id: int) -> EoaFunding | None:
    """Top a registered owner's EOA up to CHAIN_EOA_TOPUP_GAS gas units when it holds less than
    CHAIN_EOA_TOPUP_BELOW_GAS, within the funding budget; the funding row, or None when nothing
    was needed (a zero-gas chain, enough left) or the budget is spent (an operator alert says
    so; the sweep asks again). Queued by chain work that met InsufficientFunds, and the sweep."""
    chain_work_check()  # no ether goes to a reset or stalled chain
    # One top-up of an owner at a time (the one that waited finds the balance topped up); not
    # the owner's registration lock, which a sender meeting InsufficientFunds may hold.
    with exclusive(f"eoa-topup:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        owner = Owner.objects.filter(pk=owner_id, chain_state=ChainState.CONFIRMED).first()
        if owner is None:
            return None  # registration funds it
        client = chain_client()
        gas = owner_eoa_gas(owner=owner, client=client)
        if not gas.low:
            return None
        target = eoa_funding_amount(fee_per_gas=gas.fee_per_gas, gas=settings.CHAIN_EOA_TOPUP_GAS)
        if target <= gas.balance_wei:
            return None
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        tx_hash = eoa_fund(
            owner=owner,
            client=client,
            operator=operator,
            amount_wei=target - gas.balance_wei,
            reason=TOPUP_REASON,
        )
        if tx_hash is None:
            return None
        chain_activity_record(
            owner=owner,
            kind=ChainActivity.Kind.FUNDED,
            tx_hash=tx_hash,
            detail={"reason": TOPUP_REASON},
        )
    logger.info("topped up %s (%s) with %s wei", owner, owner.eoa_address, target - gas.balance_wei)
    return owner.fundings.filter(tx_hash=tx_hash).first()


def gas_sweep() -> int:
    """Queue a top-up for owners who sent lately and are low, and alert while the operator
    itself is low; how many were queued. Nothing when the node does not answer."""
    try:
        operator_balance_check()
        low = owners_low_on_gas(active_since=GAS_SCAN_ACTIVE)
    except ChainError as exc:
        logger.warning("gas sweep skipped: the chain did not answer (%s)", exc)
        return 0
    for gas in low:
        enqueue("accounts.tasks.owner_top_up", gas.owner.pk)
    return len(low)


def eoa_low_balances() -> list[LowBalance]:
    """Owners' EOAs below the top-up threshold, as the admin's chain status page lists them."""
    return [
        LowBalance(
            label=gas.owner.user.username,
            address=gas.owner.eoa_address,
            balance_wei=gas.balance_wei,
            below_wei=gas.low_below_wei,
        )
        for gas in owners_low_on_gas()
    ]
