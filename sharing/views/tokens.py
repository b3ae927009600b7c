"""Revoking an owner API token, and what it granted. Here rather than in accounts: the page
lists and revokes the grants the token made, and gives grants it changed their terms back."""

from django.contrib import messages
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_http_methods

from accounts.decorators import owner_required, page_throttle
from accounts.selectors import owner_token_of
from accounts.services.api_tokens import owner_token_revoke
from sharing.grant_terms import GrantTerms
from sharing.selectors.grants import grant_list_changed_with, grant_list_made_with
from sharing.services.grants import grants_undo_made_with


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def api_token_revoke(request: HttpRequest, token_id: int) -> HttpResponse:
    """GET: what revoking the token does, with the live grants it made and those it changed
    last; POST: revoke it, then revoke the grants it made and give the grants it changed back
    their former terms, unless the owner unticked either."""
    token = owner_token_of(request.owner, token_id)
    if token is None:
        raise Http404("no such API token")
    if request.method == "GET":
        context = {
            "token": token,
            "grants": list(grant_list_made_with(token)),
            "changed": [
                {"grant": grant, "before": GrantTerms.from_json(before)}
                for grant, before in grant_list_changed_with(token)
            ],
        }
        return render(request, "accounts/api_token_revoke.html", context)
    was_live = token.revoked_at is None
    owner_token_revoke(token=token, actor=request.user)
    undone = grants_undo_made_with(
        token=token,
        revoke_made=request.POST.get("revoke_grants") == "yes",
        restore_changed=request.POST.get("restore_grants") == "yes",
    )
    said = [f"The API token {token.name} {'is' if was_live else 'was already'} revoked."]
    if undone.revoked:
        names = ", ".join(grant.grantee.username for grant in undone.revoked)
        said.append(f"The access of {names} is revoked too; the chain follows.")
    if undone.restored:
        names = ", ".join(grant.grantee.username for grant in undone.restored)
        said.append(f"Your grants to {names} have their terms from before the token's changes.")
    messages.success(request, " ".join(said))
    return redirect("api-tokens")
