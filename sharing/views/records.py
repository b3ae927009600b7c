"""The record lists: the owner's own records, and those shared with the owner, filtered,
sorted and a page at a time, with what is missing in the window the filters select
(sharing/views/completeness.py)."""

from django.contrib import messages
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.urls import reverse
from django.views.decorators.http import require_GET

from accounts.decorators import owner_required, page_throttle
from sharing.forms import RecordFilterForm
from sharing.models import Record
from sharing.selectors.completeness import record_list_window
from sharing.selectors.grants import owners_granting
from sharing.selectors.record_pages import (
    BadCursor,
    RecordCursor,
    record_cursor_newest,
    record_page_by_capture,
)
from sharing.selectors.records import (
    record_list_filtered,
    record_list_owned,
    record_list_shared_with,
    record_list_sorted,
    robots_visible_to,
)
from sharing.views.completeness import completeness_shown
from sharing.views.filters import say_left_out

RECORDS_PER_PAGE = 25
# What a link with a cursor that does not parse is taken as: the first page, newest first.
BAD_CURSORS: dict[str, RecordCursor] = {}


@owner_required
@page_throttle()
@require_GET
def my_records(request: HttpRequest) -> HttpResponse:
    return _record_list(request, record_list_owned(request.owner), shared=False)


@owner_required
@page_throttle()
@require_GET
def shared_records(request: HttpRequest) -> HttpResponse:
    return _record_list(request, record_list_shared_with(request.owner), shared=True)


def _record_list(request: HttpRequest, records: QuerySet[Record], *, shared: bool) -> HttpResponse:
    robots = robots_visible_to(request.owner, shared=shared)
    form = RecordFilterForm(request.GET or None, records=records, robots=robots, with_owner=shared)
    context = {
        "form": form,
        "shared": shared,
        "sort": form.sort_order(),
        "total": records.live().count(),
        "granting": owners_granting(request.owner).select_related("user") if shared else None,
        # Given to each record's link, so that its page links back to this very list.
        "list_query": request.GET.urlencode(),
    }
    say_left_out(request, form)
    matching = record_list_filtered(records, **form.filters())
    cursors = _cursors(request)
    # The list as of its newest record when it was opened: later captures are counted, not
    # slid into its pages (sharing/selectors/record_pages.py).
    top = cursors.get("top") or record_cursor_newest(matching)
    if top is not None:
        context["top"] = str(top)
        context["newer"] = matching.filter(top.q_after()).count()
        matching = matching.filter(top.q_up_to())
        context["total"] = records.live().filter(top.q_up_to()).count()
        pinned = request.GET.copy()
        pinned["top"] = str(top)
        context["list_query"] = pinned.urlencode()
    sort = form.sort_order()
    if sort.removeprefix("-") == "captured":
        context["page"] = record_page_by_capture(
            matching,
            descending=sort.startswith("-"),
            size=RECORDS_PER_PAGE,
            after=cursors.get("after"),
            before=cursors.get("before"),
            last=request.GET.get("page") == "last" and cursors is not BAD_CURSORS,
        )
        context["keyset"] = True
        context["rows"] = context["page"].records
    else:
        # Other orders page by number, in the list as of `top` all the same.
        context["page"] = Paginator(record_list_sorted(matching, sort), RECORDS_PER_PAGE).get_page(
            request.GET.get("page")
        )
        context["rows"] = context["page"].object_list
    # Is anything missing in the window the filters select (any status, deletions named).
    context["completeness"] = completeness_shown(
        record_list_window(records, **form.filters()),
        list_url=reverse("shared" if shared else "records"),
    )
    return render(request, "sharing/records.html", context)


def _cursors(request: HttpRequest) -> dict[str, RecordCursor]:
    """The list's `top`, `after` and `before` cursors; one that does not parse is left out,
    said, and the list starts from its newest record again (never a 500)."""
    cursors = {}
    for name in ("top", "after", "before"):
        if text := request.GET.get(name):
            try:
                cursors[name] = RecordCursor.parse(text)
            except BadCursor:
                messages.warning(
                    request, "That page link is not valid: showing the newest records."
                )
                return BAD_CURSORS
    return cursors
