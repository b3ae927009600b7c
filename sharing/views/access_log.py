"""The access log: who read the owner's records (or the owner's own reads of records shared
with them), one line per access, filtered, a page at a time or as a CSV download."""

from django.contrib import messages
from django.db.models import QuerySet
from django.http import HttpRequest, HttpResponse, StreamingHttpResponse
from django.shortcuts import render
from django.utils import timezone
from django.views.decorators.http import require_GET

from accounts.decorators import no_store, owner_required, page_throttle
from sharing.access_log import access_log_csv, access_log_page
from sharing.forms import AccessLogFilterForm
from sharing.models import Access
from sharing.selectors.access import (
    ACCESS_LOG_DIRECTIONS,
    ACCESS_LOG_INCOMING,
    access_list_access_log,
    access_list_filtered,
    access_log_filter_choices,
    access_own,
    access_own_by_hour,
)
from sharing.views.filters import say_left_out

ACCESS_LOG_PER_PAGE = 50


@owner_required
@page_throttle()
@require_GET
def access_log(request: HttpRequest) -> HttpResponse:
    """Who read the owner's records (or, on the other tab, the owner's own reads of records
    shared with the owner), one line per access (a page, a plot...), filtered, a page at a
    time."""
    form, direction, accesses = _access_log_asked(request)
    say_left_out(request, form)
    own_hidden, own_hours = 0, []
    if _without_own_views(request, form, direction):
        # Said, summed up by the hour, with a link that lists them: left out, not lost.
        own = access_list_access_log(request.owner, direction=direction)
        own = access_list_filtered(own.filter(access_own(request.owner)), **form.filters())
        own_hidden = own.count()
        own_hours = access_own_by_hour(own) if own_hidden else []
    page = access_log_page(
        accesses, reader=request.owner, page=request.GET.get("page"), per_page=ACCESS_LOG_PER_PAGE
    )
    context = {
        "form": form,
        "direction": direction,
        "directions": ACCESS_LOG_DIRECTIONS,
        "page": page,
        "filtered": bool(form.filters()),
        "own_hidden": own_hidden,
        "own_hours": own_hours,
    }
    return render(request, "sharing/access_log.html", context)


@owner_required
@page_throttle()
@require_GET
def access_log_download(request: HttpRequest) -> HttpResponse:
    """The access log with the page's filters, every access, as a streamed CSV download. With
    a filter that does not hold, the page that says so (400): a file has no room to say it."""
    form, direction, accesses = _access_log_asked(request)
    if form.left_out():
        context = {"form": form, "direction": direction, "directions": ACCESS_LOG_DIRECTIONS}
        messages.error(request, f"No download: {form.left_out()}")
        return render(request, "sharing/access_log.html", context, status=400)
    response = StreamingHttpResponse(
        access_log_csv(accesses, reader=request.owner), content_type="text/csv; charset=utf-8"
    )
    name = f"access-log-{direction}-{timezone.now():%Y%m%dT%H%M%SZ}.csv"
    response["Content-Disposition"] = f'attachment; filename="{name}"'
    return no_store(response)


def _access_log_asked(
    request: HttpRequest,
) -> tuple[AccessLogFilterForm, str, QuerySet[Access]]:
    """The filter form, the side of the log, and the accesses its filters that hold select."""
    direction = AccessLogFilterForm.direction_of(request.GET)
    choices = access_log_filter_choices(request.owner, direction=direction)
    form = AccessLogFilterForm(request.GET or None, choices=choices)
    accesses = access_list_access_log(request.owner, direction=direction)
    if _without_own_views(request, form, direction):
        accesses = accesses.exclude(access_own(request.owner))
    return form, direction, access_list_filtered(accesses, **form.filters())


def _without_own_views(request: HttpRequest, form: AccessLogFilterForm, direction: str) -> bool:
    """Who read the owner's records is about others: the owner's own views are left out
    unless asked for (the "Include my own views" box, or the owner named as the viewer)."""
    return direction == ACCESS_LOG_INCOMING and not form.with_own_views(request.owner.username)
