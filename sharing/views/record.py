"""One record: its page, its raw JSON download, and an image topic's gallery.

The content is only shown through `record_open` / `records_open`: the worker checks access
and the stored ciphertext's SM3 digest against the chain, and the content is decrypted only
when the verdict is `verified`. The verdict is shown first, with its HTTP status. How the
content is shown is sharing/content.py.
"""

import re
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta

from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse, QueryDict
from django.shortcuts import render
from django.urls import reverse
from django.utils.http import urlencode
from django.views.decorators.http import require_GET

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.errors import IdentityMismatch
from accounts.models import Owner
from sharing.content import IMAGE_TYPES, content_of
from sharing.errors import (
    NOT_VISIBLE,
    AccessDenied,
    IntegrityCheckFailed,
    NotAnchoredYet,
    RecordDeleted,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.forms import TopicRangeForm
from sharing.models import Access, Credential, Grant, Record, Verdict
from sharing.selectors.grants import grant_ended_covering
from sharing.selectors.records import (
    record_get_visible,
    record_list_same_topic,
    record_neighbours,
    record_position_in,
)
from sharing.series import DEFAULT_POINTS
from sharing.verification.opening import OpenedRecord, record_open, records_open

# Images on one page of a topic's gallery, each integrity-checked in one batched run.
GALLERY_PER_PAGE = 12
# The range a plot or gallery form offers first, and so the range an odometry record's
# trajectory plots first (each record in it checked): this long before and after the record.
RANGE_AROUND = timedelta(minutes=5)
# A record page's refusal for a record whose anchoring failed (the worker's verdict says only
# "not anchored yet").
ANCHORING_FAILED = "anchoring_failed"
# A record page's refusal for a viewer whose grant covered the record and ended.
ACCESS_ENDED = "access_ended"


@dataclass
class Refusal:
    """Why a record's content is not shown, and with which HTTP status."""

    outcome: str
    status: int
    message: str
    record: Record | None = None
    verdict: Verdict | None = None


def _open_or_refuse(request: HttpRequest, record_id: str) -> OpenedRecord | Refusal:
    try:
        return record_open(record_id=record_id, viewer=request.owner, credential=Credential.SESSION)
    except (RecordNotFound, AccessDenied):
        # One answer whether it exists or not (the worker kept the refused view's verdict),
        # but to whom a grant once let read it: why it is no longer theirs (issue 48).
        ended = _access_ended(request.owner, record_id)
        if ended is not None:
            return Refusal(ACCESS_ENDED, 403, ended)
        return Refusal("not_found", 404, NOT_VISIBLE)
    except RecordDeleted as exc:
        # Its metadata stays (a tombstone), never TAMPERED: the ciphertext went on purpose.
        return Refusal("deleted", 410, str(exc), exc.record, exc.verdict)
    except IntegrityCheckFailed as exc:
        unsigned = (
            exc.verdict is not None and exc.verdict.outcome == Verdict.Outcome.SIGNATURE_REFUSED
        )
        outcome = Verdict.Outcome.SIGNATURE_REFUSED if unsigned else Verdict.Outcome.TAMPERED
        return Refusal(outcome, 409, str(exc), exc.record, exc.verdict)
    except NotAnchoredYet as exc:
        record = exc.record
        if record is not None and record.status == Record.Status.FAILED:
            # Not worth waiting for: it stays unanchored until an operator anchors it again.
            message = f"anchoring this record failed: {record.failure_reason or 'no reason given'}"
            return Refusal(ANCHORING_FAILED, 409, message, record, exc.verdict)
        return Refusal(Verdict.Outcome.NOT_ANCHORED_YET, 409, str(exc), record, exc.verdict)
    except VerificationUnavailable as exc:
        return Refusal("unavailable", 503, str(exc))
    except IdentityMismatch as exc:
        return Refusal(IdentityMismatch.code, IdentityMismatch.http_status, str(exc))


def _access_ended(viewer: Owner, record_id: str) -> str | None:
    """Why a grant that covered the record no longer lets `viewer` read it, or None."""
    try:
        grant = grant_ended_covering(viewer, uuid.UUID(record_id))
    except ValueError:
        return None
    if grant is None:
        return None
    if grant.status in (Grant.Status.REVOKED, Grant.Status.REVOKING):
        when = f"{grant.updated_at:%Y-%m-%d %H:%M:%S}"
        return f"access revoked by owner: {grant.owner} revoked your access on {when} UTC"
    return f"grant expired on {grant.expires_at:%Y-%m-%d %H:%M:%S} UTC: {grant.owner}'s grant ended"


@owner_required
@page_throttle()
@require_GET
def record_detail(request: HttpRequest, record_id: str) -> HttpResponse:
    opened = _open_or_refuse(request, str(record_id))
    if isinstance(opened, Refusal):
        context = {"refusal": opened, "record": opened.record, "verdict": opened.verdict}
        if opened.record is not None:
            context["nav"] = _record_nav(request, opened.record)
        return no_store(
            render(request, "sharing/record_detail.html", context, status=opened.status)
        )
    record = opened.record
    if record.block_number is None:
        # Anchored between this page's read of the row and the worker's check: show the block
        # and transaction anchoring wrote since (if it has yet), not the row read before.
        record.refresh_from_db()
    content = content_of(data_type=record.data_type, plaintext=opened.plaintext)
    context = {
        "nav": _record_nav(request, record),
        "record": record,
        "verdict": opened.verdict,
        "header": opened.header,
        "content": content,
        "ros_seq": content.ros_seq,
        "is_own": record.owner_id == request.owner.pk,
    }
    if content.is_odometry:
        context.update(_plot_of(request, record))
    return no_store(render(request, "sharing/record_detail.html", context))


@dataclass(frozen=True)
class RecordNav:
    """A record page's way around: the previous and next record of its robot and topic, and
    the list it was opened from, with that list's filters (the `list` parameter)."""

    previous: Record | None
    next: Record | None
    list_url: str
    # Given on to the previous and next records' links, so that "back" stays the same list.
    suffix: str


def _record_nav(request: HttpRequest, record: Record) -> RecordNav:
    previous, following = record_neighbours(record, viewer=request.owner)
    is_own = record.owner_id == request.owner.pk
    # Only a query string is taken from the link, re-encoded: "back" stays on this portal.
    list_query = QueryDict(request.GET.get("list", "")).urlencode()
    list_url = reverse("records" if is_own else "shared")
    return RecordNav(
        previous,
        following,
        f"{list_url}?{list_query}" if list_query else list_url,
        f"?{urlencode({'list': list_query})}" if list_query else "",
    )


def _plot_of(request: HttpRequest, record: Record) -> dict[str, object]:
    """The range form and the range the page's trajectory plot (static/portal/series-plot.js,
    from the series API) covers: the one asked for, else the one the form offers first
    (RANGE_AROUND either side, whole minutes), the same the form shows."""
    form = TopicRangeForm(_range_given(request) or None)
    if form.is_bound and form.is_valid():
        since, until = form.cleaned_data["since"], form.cleaned_data["until"]
    else:
        around = _range_form_around(record)
        since, until = around.initial["since"], around.initial["until"]
        if not form.is_bound:
            form = around
    return {
        "range_form": form,
        "plot_since": since,
        "plot_until": until,
        "plot_points": DEFAULT_POINTS,
    }


def _range_given(request: HttpRequest) -> dict[str, str]:
    return {name: request.GET[name] for name in ("since", "until") if name in request.GET}


def _range_form_around(record: Record) -> TopicRangeForm:
    """The range form filled with RANGE_AROUND either side of the record, whole minutes."""
    since = (record.captured_at - RANGE_AROUND).replace(second=0, microsecond=0)
    until = (record.captured_at + RANGE_AROUND).replace(second=0, microsecond=0)
    return TopicRangeForm(initial={"since": since, "until": until})


def _range_of(request: HttpRequest, record: Record) -> TopicRangeForm:
    """The range asked for, or (none asked for) the default around the record, bound."""
    given = _range_given(request)
    if not given:
        initial = _range_form_around(record).initial
        given = {name: _local(initial[name]) for name in ("since", "until")}
    return TopicRangeForm(given)


def _local(moment: datetime) -> str:
    return moment.strftime("%Y-%m-%dT%H:%M")


@owner_required
@page_throttle()
@require_GET
def record_raw(request: HttpRequest, record_id: str) -> HttpResponse:
    """The decrypted Fig. 4 JSON as a download, after the same integrity check."""
    opened = _open_or_refuse(request, str(record_id))
    if isinstance(opened, Refusal):
        return no_store(
            JsonResponse({"error": opened.outcome, "detail": opened.message}, status=opened.status)
        )
    response = HttpResponse(opened.plaintext, content_type="application/json")
    response["Content-Disposition"] = f'attachment; filename="{_download_name(opened.record)}"'
    return no_store(response)


def _plain_refusal(message: str, status: int) -> HttpResponse:
    return no_store(HttpResponse(message, status=status, content_type="text/plain"))


@owner_required
@page_throttle()
@require_GET
def record_gallery(request: HttpRequest, record_id: str) -> HttpResponse:
    """The images of an image record's topic captured in a time range, GALLERY_PER_PAGE a
    page, oldest first; each one integrity-checked (in one batched run) before it is shown."""
    record = record_get_visible(request.owner, record_id)
    if record is None:
        raise Http404(NOT_VISIBLE)
    if record.data_type not in IMAGE_TYPES:
        raise Http404("only image records have a gallery")
    form = _range_of(request, record)
    context = {"record": record, "form": form}
    if not form.is_valid():
        return no_store(render(request, "sharing/gallery.html", context, status=400))
    in_range = record_list_same_topic(
        request.owner, record, since=form.cleaned_data["since"], until=form.cleaned_data["until"]
    )
    page = Paginator(in_range, GALLERY_PER_PAGE).get_page(
        request.GET.get("page") or _gallery_page_of(in_range, record)
    )
    results = records_open(
        records=list(page.object_list),
        viewer=request.owner,
        kind=Access.Kind.PAGE,
        credential=Credential.SESSION,
    )
    context["page"] = page
    context["tiles"] = [
        _gallery_tile(item, result) for item, result in zip(page, results, strict=True)
    ]
    return no_store(render(request, "sharing/gallery.html", context))


def _gallery_page_of(in_range: QuerySet[Record], record: Record) -> int:
    """The page of the gallery that shows the record (where it would be, outside the range)."""
    return record_position_in(in_range, record) // GALLERY_PER_PAGE + 1


@dataclass
class GalleryTile:
    """One image of a gallery, or why it is not shown."""

    record: Record
    image_url: str = ""
    refused: str = ""


def _gallery_tile(record: Record, result: OpenedRecord | SharingError) -> GalleryTile:
    if isinstance(result, IntegrityCheckFailed):
        return GalleryTile(record, refused="TAMPERED: not shown")
    if isinstance(result, SharingError):
        return GalleryTile(record, refused=f"not shown: {result}")
    content = content_of(data_type=record.data_type, plaintext=result.plaintext)
    if not content.image_url:
        return GalleryTile(record, refused="verified, but holds no PNG or JPEG image")
    return GalleryTile(record, image_url=content.image_url)


def _download_name(record: Record) -> str:
    topic = re.sub(r"[^A-Za-z0-9_.-]+", "_", record.topic).strip("_") or "record"
    return f"{topic}-{record.seq}-{record.pk}.json"
