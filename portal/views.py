"""The project's own pages, which span both apps: the front page and the dashboard.

The front page only sends each visitor where they belong. Every page but registration and
sign-in needs a login, so anonymous visitors go to the sign-in page; nothing there calls the
chain or tells how the portal is deployed (operators see the chain's status in the admin
console).
"""

from decimal import Decimal

from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.views.decorators.http import require_GET

from accounts.decorators import owner_required
from accounts.models import ChainState, Owner
from accounts.selectors import (
    owner_balance_wei,
    owner_for_user,
    owner_key_current,
    robot_count_active,
)
from chainworker.chain import ChainError
from sharing.selectors import grant_count_given, grant_count_received, record_list_owned

WEI_PER_ETHER = Decimal(10) ** 18


def home(request: HttpRequest) -> HttpResponse:
    if not request.user.is_authenticated:
        return redirect("login")
    if owner_for_user(request.user) is None and request.user.is_staff:
        return redirect("admin:index")
    # Owners, and accounts that are neither (the dashboard tells them they are no owner).
    return redirect("dashboard")


@owner_required
@require_GET
def dashboard(request: HttpRequest) -> HttpResponse:
    """The owner's identity on chain, with its EOA balance, and what it has and shares."""
    owner: Owner = request.owner
    balance, chain_problem = None, None
    try:
        balance = Decimal(owner_balance_wei(owner)) / WEI_PER_ETHER
    except ChainError as exc:
        chain_problem = f"The chain node is not reachable right now ({exc.__class__.__name__})."
    context = {
        "owner": owner,
        "key": owner_key_current(owner),
        "balance": balance,
        "chain_problem": chain_problem,
        "confirmed": owner.chain_state == ChainState.CONFIRMED,
        "failed": owner.chain_state == ChainState.FAILED,
        "record_count": record_list_owned(owner).count(),
        "grants_given_count": grant_count_given(owner),
        "grants_received_count": grant_count_received(owner),
        "robot_count": robot_count_active(owner),
    }
    return render(request, "portal/dashboard.html", context)
