"""Deleting: one record, a selection of the owner's records (with a preview first), or the
whole account (here rather than in accounts: it deletes records and revokes grants too)."""

from django.contrib import messages
from django.contrib.auth import logout
from django.core.exceptions import PermissionDenied
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_http_methods

from accounts.decorators import owner_required, page_throttle
from accounts.errors import WrongPassword
from accounts.models import Owner
from sharing.errors import NotRecordOwner, RecordNotFound, SharingError
from sharing.forms import AccountDeleteForm, RecordDeleteSelectionForm
from sharing.models import Grant, Record
from sharing.selectors.grants import grant_list_given, grant_list_received
from sharing.selectors.records import record_list_owned
from sharing.services.deletion import (
    account_delete,
    record_delete,
    record_selection,
    records_delete,
)


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def record_delete_view(request: HttpRequest, record_id: str) -> HttpResponse:
    """GET: what deleting the record does, to confirm; POST: delete it."""
    owner: Owner = request.owner
    if request.method == "GET":
        record = record_list_owned(owner).live().filter(pk=record_id).first()
        if record is None:
            raise Http404("no such record of yours")
        return render(request, "sharing/record_delete.html", {"record": record})
    try:
        record = record_delete(owner=owner, record_id=record_id, actor=request.user)
    except RecordNotFound:
        raise Http404("no such record of yours") from None
    except NotRecordOwner as exc:
        raise PermissionDenied(str(exc)) from None
    except SharingError as exc:
        messages.error(request, str(exc))
        return redirect("record-detail", record_id=record_id)
    messages.success(
        request,
        f"The record {record.topic} #{record.seq} is deleted: its data is removed; its digest "
        "stays on chain.",
    )
    return redirect("record-detail", record_id=record.pk)


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def records_delete_view(request: HttpRequest) -> HttpResponse:
    """GET: choose a selection (robot, topic, time range) and see what it holds; POST (from
    that preview, the same selection): delete it."""
    owner: Owner = request.owner
    data = request.POST if request.method == "POST" else request.GET
    form = RecordDeleteSelectionForm(data or None, owner=owner)
    if not form.is_bound or not form.is_valid():
        status = 400 if form.is_bound else 200
        return render(request, "sharing/records_delete.html", {"form": form}, status=status)
    selection = form.selection()
    if request.method == "POST":
        done = records_delete(owner=owner, actor=request.user, **selection)
        said = f"{done.deleted} record{'s' if done.deleted != 1 else ''} deleted."
        if done.not_anchored:
            said += f" {done.not_anchored} not anchored yet were kept: delete them once anchored."
        messages.success(request, said)
        return redirect("records")
    selected = record_selection(owner, **selection)
    context = {
        "form": form,
        "preview": True,
        "anchored": selected.filter(status=Record.Status.ANCHORED).count(),
        "not_anchored": selected.exclude(status=Record.Status.ANCHORED).count(),
    }
    return render(request, "sharing/records_delete.html", context)


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def account_delete_view(request: HttpRequest) -> HttpResponse:
    """GET: what deleting the account does; POST, with the password again: delete it."""
    owner: Owner = request.owner
    form = AccountDeleteForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            account_delete(owner=owner, password=form.cleaned_data["password"])
        except WrongPassword:
            form.add_error("password", "This is not your password: nothing was deleted.")
        else:
            username = owner.username
            logout(request)
            return render(request, "sharing/account_deleted.html", {"username": username})
    context = {
        "form": form,
        "owner": owner,
        "records": record_list_owned(owner).live().count(),
        "given": grant_list_given(owner).filter(status__in=Grant.LIVE).count(),
        "received": grant_list_received(owner).filter(status__in=Grant.LIVE).count(),
    }
    status = 400 if form.is_bound else 200
    return render(request, "sharing/account_delete.html", context, status=status)
