"""The portal's front page: owners go to their dashboard, everyone else sees what runs."""

from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect, render

from accounts.selectors import owner_for_user
from chainworker.chain import ChainError
from chainworker.services import chain_status


def home(request: HttpRequest) -> HttpResponse:
    if owner_for_user(request.user) is not None:
        return redirect("dashboard")
    try:
        status = chain_status()
        problem = status.get("problem")
    except ChainError as exc:
        status, problem = None, f"The chain node is not reachable: {exc}"
    return render(request, "portal/home.html", {"status": status, "problem": problem})
