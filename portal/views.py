"""The project's own pages, which span both apps: the front page, the dashboard and the
owner's security page (account events and record alarms together).

The front page only sends each visitor where they belong. Every page but registration and
sign-in needs a login, so anonymous visitors go to the sign-in page; nothing there calls the
chain or tells how the portal is deployed (operators see the chain's status in the admin
console).
"""

import heapq
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta
from decimal import Decimal
from itertools import islice

from django.core.paginator import Paginator
from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.utils import timezone
from django.views.decorators.http import require_GET

from accounts.decorators import owner_required, page_throttle
from accounts.forms import PairingCodeForm
from accounts.models import AccountEvent, ChainState, Owner
from accounts.selectors import (
    account_events_of,
    account_events_to_notice,
    owner_for_user,
    owner_key_current,
    robot_any_of,
    robot_count_active,
)
from accounts.services.funding import owner_eoa_gas
from chainworker.errors import ChainError
from sharing.models import SecurityEvent
from sharing.selectors.activity import security_events_of
from sharing.selectors.grants import grant_count_given, grant_count_received
from sharing.selectors.records import record_counts_of

WEI_PER_ETHER = Decimal(10) ** 18
SECURITY_EVENTS_PER_PAGE = 50
# How long the dashboard points to an operator's action or an alarm.
SECURITY_NOTICE_DAYS = 7


def home(request: HttpRequest) -> HttpResponse:
    if not request.user.is_authenticated:
        return redirect("login")
    if owner_for_user(request.user) is None and request.user.is_staff:
        return redirect("admin:index")
    # Owners, and accounts that are neither (the dashboard tells them they are no owner).
    return redirect("dashboard")


@owner_required
@page_throttle()
@require_GET
def dashboard(request: HttpRequest) -> HttpResponse:
    """The owner's identity on chain, with its EOA balance, and what it has and shares; an
    owner with no robot yet is first shown how to pair one (install, pair, approve), with the
    commands for the address this page was asked at."""
    owner: Owner = request.owner
    balance, gas, chain_problem = None, None, None
    try:
        gas = owner_eoa_gas(owner=owner)
        balance = Decimal(gas.balance_wei) / WEI_PER_ETHER
    except ChainError as exc:
        chain_problem = f"The chain node is not reachable right now ({exc.__class__.__name__})."
    context = {
        "owner": owner,
        "key": owner_key_current(owner),
        "balance": balance,
        "gas": gas,
        "gas_low_below": Decimal(gas.low_below_wei) / WEI_PER_ETHER if gas else None,
        "chain_problem": chain_problem,
        "confirmed": owner.chain_state == ChainState.CONFIRMED,
        "failed": owner.chain_state == ChainState.FAILED,
        "record_counts": record_counts_of(owner),
        "grants_given_count": grant_count_given(owner),
        "grants_received_count": grant_count_received(owner),
        "robot_count": robot_count_active(owner),
        "security_notice": _security_notice(owner),
        "first_robot": not robot_any_of(owner),
        "code_form": PairingCodeForm(),
    }
    return render(request, "portal/dashboard.html", context)


def _security_notice(owner: Owner) -> bool:
    """An operator's action or an alarm in the last SECURITY_NOTICE_DAYS days."""
    since = timezone.now() - timedelta(days=SECURITY_NOTICE_DAYS)
    return (
        account_events_to_notice(owner, since=since).exists()
        or security_events_of(owner, since=since).exists()
    )


# --- security page -----------------------------------------------------------------------------


@dataclass(frozen=True)
class SecurityEntry:
    """One line of the security page, from either table."""

    at: datetime
    kind: str
    title: str
    actor: str
    by_operator: bool
    alarm: bool
    detail: list[tuple[str, str]]
    record_id: uuid.UUID | None


class SecurityEntries:
    """An owner's account events and record alarms as one newest-first list that the
    Paginator slices: a page reads at most (its last index) rows of each table."""

    def __init__(self, owner: Owner) -> None:
        self.owner = owner

    def count(self) -> int:
        return account_events_of(self.owner).count() + security_events_of(self.owner).count()

    def __getitem__(self, index: slice) -> list[SecurityEntry]:
        stop = index.stop
        account = (self._account_entry(e) for e in account_events_of(self.owner)[:stop])
        alarms = (self._alarm_entry(e) for e in security_events_of(self.owner)[:stop])
        merged = heapq.merge(account, alarms, key=lambda entry: entry.at, reverse=True)
        return list(islice(merged, index.start, stop))

    def _account_entry(self, event: AccountEvent) -> SecurityEntry:
        if event.actor_id is None:
            actor, by_operator = "the portal", False
        elif event.actor_id == self.owner.user_id:
            actor, by_operator = "you", False
        else:
            actor, by_operator = f"operator {event.actor.get_username()}", True
        return SecurityEntry(
            at=event.created_at,
            kind=event.kind,
            title=event.get_kind_display(),
            actor=actor,
            by_operator=by_operator,
            alarm=event.kind in AccountEvent.ALARM_KINDS,
            detail=_detail_lines(event.detail),
            record_id=None,
        )

    def _alarm_entry(self, event: SecurityEvent) -> SecurityEntry:
        return SecurityEntry(
            at=event.created_at,
            kind=event.kind,
            title=event.get_kind_display(),
            actor="the portal",
            by_operator=False,
            alarm=True,
            detail=_detail_lines(event.detail),
            record_id=event.record_id,
        )


def _detail_lines(detail: object) -> list[tuple[str, str]]:
    if not isinstance(detail, dict):
        return [("detail", str(detail))]
    return [
        (str(key), ", ".join(map(str, value)) if isinstance(value, list) else str(value))
        for key, value in detail.items()
    ]


@owner_required
@page_throttle()
@require_GET
def security(request: HttpRequest) -> HttpResponse:
    """What happened to the owner's account (operators' actions, credentials, identity
    checks) and alarms about its records, newest first."""
    owner: Owner = request.owner
    entries = SecurityEntries(owner)
    page = Paginator(entries, SECURITY_EVENTS_PER_PAGE).get_page(request.GET.get("page"))
    return render(request, "portal/security.html", {"page": page, "owner": owner})
