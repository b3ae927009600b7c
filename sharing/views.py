"""Owner pages of the sharing app: my data, shared with me, a record, grants, audit.

A record's content is only ever shown through `records_open` (`record_open` for one): the
worker checks access and the stored ciphertext's SM3 digest against the chain, and the
content is decrypted only when the verdict is `verified`. The verdict is shown first, with
its HTTP status. How the content is shown is sharing/content.py; the audit trail's entries
are sharing/audit.py.
"""

import re
import uuid
from dataclasses import dataclass
from datetime import datetime, timedelta

from django.contrib import messages
from django.contrib.auth import logout
from django.core.exceptions import PermissionDenied
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import (
    Http404,
    HttpRequest,
    HttpResponse,
    JsonResponse,
    QueryDict,
    StreamingHttpResponse,
)
from django.shortcuts import redirect, render
from django.urls import reverse
from django.utils import timezone
from django.utils.http import urlencode
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.errors import IdentityMismatch, WrongPassword
from accounts.models import Owner
from accounts.selectors import owner_by_identifier, owner_token_of, robot_list_of
from accounts.services.api_tokens import owner_token_revoke
from sharing.access_log import access_log_csv, access_log_page
from sharing.audit import audit_page_of_owner
from sharing.content import IMAGE_TYPES, content_of
from sharing.deletion import (
    account_delete,
    record_delete,
    record_selection,
    records_delete,
)
from sharing.errors import (
    NOT_VISIBLE,
    AccessDenied,
    ExportNotFound,
    ExportRefused,
    IntegrityCheckFailed,
    InvalidGrantTerms,
    NotAnchoredYet,
    NotRecordOwner,
    RecordDeleted,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.exports.create import export_create, export_rebuild
from sharing.exports.download import export_current
from sharing.exports.selection import (
    export_count,
    export_robots_visible,
    export_selection_described,
    export_topics_visible,
)
from sharing.forms import (
    AccessLogFilterForm,
    AccountDeleteForm,
    AuditFilterForm,
    ExportForm,
    GrantForm,
    GrantRevokeForm,
    PeriodFilterForm,
    RecordDeleteSelectionForm,
    RecordFilterForm,
    TopicRangeForm,
)
from sharing.models import Access, Credential, Grant, Record, Verdict
from sharing.selectors import (
    ACCESS_LOG_DIRECTIONS,
    access_list_access_log,
    access_list_filtered,
    access_log_filter_choices,
    export_list_of,
    grant_list_changed_with,
    grant_list_given,
    grant_list_made_with,
    grant_list_received,
    grant_terms_of,
    grant_topic_choices,
    grants_described,
    owners_granting,
    record_get_visible,
    record_list_filtered,
    record_list_owned,
    record_list_same_topic,
    record_list_shared_with,
    record_list_sorted,
    record_neighbours,
    record_position_in,
    robots_visible_to,
)
from sharing.series import DEFAULT_POINTS
from sharing.services import (
    GrantTerms,
    grant_create,
    grant_create_check,
    grant_revoke,
    grant_terms_change,
    grant_terms_make,
    grants_undo_made_with,
    owner_resolve,
)
from sharing.verification.opening import OpenedRecord, record_open, records_open

RECORDS_PER_PAGE = 25
# Minutes of anchoring on one page of the audit trail.
AUDIT_ENTRIES_PER_PAGE = 50
ACCESS_LOG_PER_PAGE = 50
# The trajectory on an odometry record's page: every record of its robot's topic this long
# before and after it (the range form chooses another), each checked (sharing/series.py).
PLOT_AROUND = timedelta(minutes=1)
# Images on one page of a topic's gallery, each integrity-checked in one batched run.
GALLERY_PER_PAGE = 12
GALLERY_COST = 6
# The range a plot or gallery form offers first: this long before and after the record.
RANGE_AROUND = timedelta(minutes=5)
# A record page's refusal for a record whose anchoring failed (the worker's verdict says only
# "not anchored yet").
ANCHORING_FAILED = "anchoring_failed"


# --- record lists --------------------------------------------------------------------------


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
        "total": records.filter(deleted_at__isnull=True).count(),
        "granting": owners_granting(request.owner).select_related("user") if shared else None,
        # Given to each record's link, so that its page links back to this very list.
        "list_query": request.GET.urlencode(),
    }
    _say_left_out(request, form)
    filtered = record_list_sorted(
        record_list_filtered(records, **form.filters()), form.sort_order()
    )
    # The count is one COUNT over the index of the filter (sharing 0006): measured at about
    # 5 ms for 100,000 records of one owner on SQLite, less than the page's own query.
    page = Paginator(filtered, RECORDS_PER_PAGE).get_page(request.GET.get("page"))
    context["page"] = page
    return render(request, "sharing/records.html", context)


def _say_left_out(request: HttpRequest, form: PeriodFilterForm) -> None:
    """A list page answers with the filters that hold; this says which were left out."""
    if said := form.left_out():
        messages.warning(request, said)


# --- one record ----------------------------------------------------------------------------


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
        # One answer whether it exists or not (the worker kept the refused view's verdict).
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


@owner_required
@page_throttle("content")
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
    from the series API) covers: the one asked for, else PLOT_AROUND either side."""
    form = TopicRangeForm(_range_given(request) or None)
    if form.is_bound and form.is_valid():
        since, until = form.cleaned_data["since"], form.cleaned_data["until"]
    else:
        since, until = record.captured_at - PLOT_AROUND, record.captured_at + PLOT_AROUND
    if not form.is_bound:
        form = _range_form_around(record)
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


# --- deleting records ------------------------------------------------------------------------


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def record_delete_view(request: HttpRequest, record_id: str) -> HttpResponse:
    """GET: what deleting the record does, to confirm; POST: delete it."""
    owner: Owner = request.owner
    if request.method == "GET":
        record = record_list_owned(owner).filter(pk=record_id, deleted_at__isnull=True).first()
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
    selection = form.filters()
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


# --- deleting the account ----------------------------------------------------------------------
# Here rather than in accounts: it deletes records and revokes grants too.


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
        "records": record_list_owned(owner).filter(deleted_at__isnull=True).count(),
        "given": grant_list_given(owner).filter(status__in=Grant.LIVE).count(),
        "received": grant_list_received(owner).filter(status__in=Grant.LIVE).count(),
    }
    status = 400 if form.is_bound else 200
    return render(request, "sharing/account_delete.html", context, status=status)


@owner_required
@page_throttle("content")
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
@page_throttle("content", cost=GALLERY_COST)
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


# --- grants --------------------------------------------------------------------------------


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
        "waiting": any(
            g.status in (Grant.Status.PENDING, Grant.Status.REVOKING) for g in given + received
        ),
    }
    return render(request, "sharing/grants.html", context, status=400 if form.is_bound else 200)


def _grant_give_or_change(request: HttpRequest, form: GrantForm) -> HttpResponse | None:
    """Call the service; the redirect on success, None with the form's errors added."""
    data = form.cleaned_data
    try:
        grantee = owner_resolve(data["grantee"])
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
            owner=request.owner,
            robots=data["robots"],
            topics=data["topics"],
            since=data["since"],
            until=data["until"],
            expires_at=data["expires_at"],
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
    if data["change"]:
        said = (
            f"The new terms of {grantee}'s access are being written to the chain: {grantee} "
            "may read what they cover once they are confirmed there."
        )
    else:
        said = (
            f"The grant to {grantee} is being written to the chain: {grantee} may read your "
            "records once it is confirmed there."
        )
    messages.success(request, said)
    return redirect("grants")


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


# --- audit ---------------------------------------------------------------------------------


@owner_required
@page_throttle()
@require_GET
def audit(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = AuditFilterForm(request.GET or None, owner=owner)
    _say_left_out(request, form)
    trail = audit_page_of_owner(
        owner, page=request.GET.get("page"), per_page=AUDIT_ENTRIES_PER_PAGE, **form.filters()
    )
    context = {
        "form": form,
        "trail": trail,
        "page": trail.anchoring,
        "owner": owner,
        "filtered": bool(form.filters()),
    }
    return render(request, "sharing/audit.html", context)


# --- access log ----------------------------------------------------------------------------


@owner_required
@page_throttle()
@require_GET
def access_log(request: HttpRequest) -> HttpResponse:
    """Who read the owner's records (or, on the other tab, the owner's own reads of records
    shared with the owner), one line per access (a page, a plot...), filtered, a page at a
    time."""
    form, direction, accesses = _access_log_asked(request)
    _say_left_out(request, form)
    page = access_log_page(
        accesses, reader=request.owner, page=request.GET.get("page"), per_page=ACCESS_LOG_PER_PAGE
    )
    context = {
        "form": form,
        "direction": direction,
        "directions": ACCESS_LOG_DIRECTIONS,
        "page": page,
        "filtered": bool(form.filters()),
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
    return form, direction, access_list_filtered(accesses, **form.filters())


# --- revoking an owner API token, and what it granted ----------------------------------------
# Here rather than in accounts: the page lists and revokes the grants the token made.


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


# --- exports ---------------------------------------------------------------------------------


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
        selection = {
            name: form.cleaned_data.get(name) for name in ("robots", "topics", "since", "until")
        }
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
