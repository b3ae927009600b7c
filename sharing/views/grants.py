"""The grants page: giving access, changing a grant's terms (with a confirmation page for a
grant of everything), and revoking, with the lists of grants given and received."""

from urllib.parse import urlencode

from django.contrib import messages
from django.http import HttpRequest, HttpResponse, QueryDict
from django.shortcuts import redirect, render
from django.urls import reverse
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.decorators import owner_required, page_throttle
from accounts.models import Owner
from accounts.selectors import owner_by_identifier, robot_list_of
from sharing.errors import InvalidGrantTerms, SharingError
from sharing.forms import GrantForm, GrantRevokeForm
from sharing.grant_terms import grant_terms_make
from sharing.models import Grant
from sharing.selectors.grants import (
    grant_list_given,
    grant_list_received,
    grant_terms_of,
    grant_topic_choices,
    grantee_resolve,
    grants_described,
    owner_resolve,
)
from sharing.services.grants import (
    grant_create,
    grant_create_check,
    grant_revoke,
    grant_terms_change,
)


@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def grants(request: HttpRequest) -> HttpResponse:
    """Give access, or (`change`) change the terms of a grant given; the lists of both sides.
    GET ?change=<grantee> fills the form with that grant's terms."""
    owner: Owner = request.owner
    robots = robot_list_of(owner)
    choices = {"robots": robots, "topics": grant_topic_choices(owner, robots)}
    if request.method == "POST":
        form = GrantForm(request.POST, **choices)
        if form.is_valid() and (done := _grant_give_or_change(request, form)) is not None:
            return done
    else:
        asked = request.GET.get("change")
        initial = _grant_change_initial(owner, asked)
        if asked and not initial:
            messages.warning(request, "You give that owner no access to change: nothing filled in.")
        form = GrantForm(initial=initial, **choices)
    given = grants_described(grant_list_given(owner))
    received = grants_described(grant_list_received(owner))
    context = {
        "form": form,
        "changing": form.fields["change"].to_python(form["change"].value()),
        "given": given,
        "received": received,
        "owner": owner,
        # A grant or revocation still on its way to the chain: the page follows it.
        "made": _grant_said(owner, request.GET) if request.method == "GET" else "",
        "waiting": any(
            g.status in (Grant.Status.PENDING, Grant.Status.REVOKING) for g in given + received
        ),
    }
    return render(request, "sharing/grants.html", context, status=400 if form.is_bound else 200)


def _grant_give_or_change(request: HttpRequest, form: GrantForm) -> HttpResponse | None:
    """Call the service; the redirect on success, None with the form's errors added."""
    data = form.cleaned_data
    try:
        resolve = owner_resolve if data["change"] else grantee_resolve
        grantee = resolve(data["grantee"])
    except SharingError as exc:
        form.add_error("grantee", str(exc))
        return None
    if form.needs_confirmation:
        # Nothing is granted yet: refusals first, then a page that says what "everything"
        # means and asks again.
        if not data["change"]:
            try:
                grant_create_check(owner=request.owner, grantee=grantee)
            except SharingError as exc:
                form.add_error("grantee", str(exc))
                return None
        context = {"form": form, "grantee": grantee, "changing": data["change"]}
        return render(request, "sharing/grant_confirm_all.html", context)
    try:
        terms = grant_terms_make(
            owner=request.owner, **form.selection(), expires_at=data["expires_at"]
        )
        if data["change"]:
            grant_terms_change(owner=request.owner, grantee=grantee, terms=terms)
        else:
            grant_create(owner=request.owner, grantee=grantee, made_with="session", terms=terms)
    except InvalidGrantTerms as exc:
        form.add_error(None, str(exc))
        return None
    except SharingError as exc:
        form.add_error("grantee", str(exc))
        return None
    # The page says what the grant is when it shows its row (_grant_said), not what it was now.
    made = urlencode({"made": grantee.username, **({"changed": "1"} if data["change"] else {})})
    return redirect(f"{reverse('grants')}?{made}")


def _grant_said(owner: Owner, query: QueryDict) -> str:
    """What the grant just made (or changed, `?made=<grantee>&changed=1`) is, as its row says
    as the page is shown: confirmed on chain (the worker may be that quick) or still being
    written there (issue 48); "" for no such grant."""
    grantee = owner_by_identifier(query.get("made", ""))
    grant = grant_terms_of(owner, grantee) if grantee is not None else None
    if grant is None:
        return ""
    changed = query.get("changed") == "1"
    what = f"The new terms of {grantee}'s access are" if changed else f"The grant to {grantee} is"
    covers = "they cover" if changed else "it covers"
    if grant.status == Grant.Status.ACTIVE:
        return f"{what} confirmed on chain: {grantee} may read what {covers}."
    return (
        f"{what} being written to the chain: {grantee} may read what {covers} once its row "
        "below says active."
    )


def _grant_change_initial(owner: Owner, grantee_name: str | None) -> dict[str, object]:
    """The form's values for changing the owner's grant to `grantee_name`, if it has one."""
    if not grantee_name:
        return {}
    grantee = owner_by_identifier(grantee_name)
    grant = grant_terms_of(owner, grantee) if grantee is not None else None
    if grant is None:
        return {}
    return {
        "grantee": grantee.username,
        "robots": grant.scope_robots,
        "topics": grant.scope_topics,
        "since": grant.scope_since,
        "until": grant.scope_until,
        "expires_at": grant.expires_at,
        "change": True,
    }


@never_cache
@owner_required
@page_throttle()
@require_GET
def grant_revoke_confirm(request: HttpRequest) -> HttpResponse:
    """What revoking a grant does, and the button that does it (the grants page links here)."""
    form = GrantRevokeForm(request.GET)
    grantee = owner_by_identifier(form.cleaned_data["grantee"]) if form.is_valid() else None
    grant = grant_terms_of(request.owner, grantee) if grantee is not None else None
    if grant is None:
        messages.error(request, "There is no access to revoke for that owner.")
        return redirect("grants")
    context = {"grant": grants_described([grant])[0]}
    return render(request, "sharing/grant_revoke_confirm.html", context)


@owner_required
@page_throttle()
@require_POST
def grant_revoke_view(request: HttpRequest) -> HttpResponse:
    form = GrantRevokeForm(request.POST)
    if not form.is_valid():
        messages.error(request, "Say whose access to revoke.")
        return redirect("grants")
    try:
        grantee = owner_resolve(form.cleaned_data["grantee"])
        grant_revoke(owner=request.owner, grantee=grantee)
    except SharingError as exc:
        messages.error(request, str(exc))
    else:
        messages.success(
            request,
            f"{grantee} can no longer read your records; the revocation is being written to "
            "the chain.",
        )
    return redirect("grants")
