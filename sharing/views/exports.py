"""The export pages: the export form (count, or export a selection) with the owner's
exports, an export's progress and files, and rebuilding one under the owner's access now."""

import uuid

from django.contrib import messages
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.models import Owner
from sharing.errors import ExportNotFound, ExportRefused
from sharing.exports.create import export_create, export_rebuild
from sharing.exports.download import export_current
from sharing.exports.selection import (
    export_count,
    export_robots_visible,
    export_selection_described,
    export_topics_visible,
)
from sharing.forms import ExportForm
from sharing.models import Credential
from sharing.selectors.exports import export_list_of


@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def exports(request: HttpRequest) -> HttpResponse:
    """GET: the export form and the owner's exports; POST: count the selection's records
    (the "Count records" button) or start its export."""
    owner: Owner = request.owner
    form = ExportForm(
        request.POST if request.method == "POST" else None,
        robots=export_robots_visible(owner),
        topics=export_topics_visible(owner),
    )
    counted = None
    if request.method == "POST" and form.is_valid():
        selection = form.selection()
        try:
            if "count" in request.POST:
                counted = export_count(requester=owner, **selection)
            else:
                export = export_create(requester=owner, credential=Credential.SESSION, **selection)
                return redirect("export-detail", export_id=export.pk)
        except ExportRefused as exc:
            form.add_error(None, str(exc))
    refused = form.is_bound and (not form.is_valid() or bool(counted and counted.refusal))
    context = {"form": form, "counted": counted, "exports": export_list_of(owner)[:20]}
    return render(request, "sharing/exports.html", context, status=400 if refused else 200)


@owner_required
@page_throttle()
@require_GET
def export_detail(request: HttpRequest, export_id: uuid.UUID) -> HttpResponse:
    """An export's progress (updating itself while it runs), then its files, its selection
    and the command that checks them; withdrawn, with why, once access to its records ended."""
    try:
        export = export_current(requester=request.owner, export_id=export_id)
    except ExportNotFound:
        raise Http404("no such export of yours") from None
    context = {"export": export, "selection": export_selection_described(export)}
    return no_store(render(request, "sharing/export_detail.html", context))


@owner_required
@page_throttle()
@require_POST
def export_rebuild_view(request: HttpRequest, export_id: uuid.UUID) -> HttpResponse:
    """Export an export's selection again, under the owner's access now."""
    try:
        export = export_rebuild(
            requester=request.owner,
            export_id=export_id,
            credential=Credential.SESSION,
        )
    except ExportNotFound:
        raise Http404("no such export of yours") from None
    except ExportRefused as exc:
        messages.error(request, f"Not exported again: {exc}.")
        return redirect("export-detail", export_id=export_id)
    return redirect("export-detail", export_id=export.pk)
