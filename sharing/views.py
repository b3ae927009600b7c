"""Owner pages of the sharing app: my data, shared with me, a record, grants, audit.

A record's content is only ever shown through `record_open`: the worker checks access and
the stored ciphertext's SM3 digest against the chain, and the content is decrypted only
when the verdict is `verified`. The verdict is shown first, with its HTTP status. How the
content is shown is sharing/content.py; the audit trail's entries are sharing/audit.py.
"""

import re
from dataclasses import dataclass

from django.contrib import messages
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import redirect, render
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.errors import IdentityMismatch
from accounts.models import Owner
from accounts.selectors import owner_token_of
from accounts.services import owner_token_revoke
from sharing.audit import audit_page_of_owner
from sharing.content import ODOMETRY, content_of, pose_of, trajectory_plot
from sharing.errors import (
    AccessDenied,
    IntegrityCheckFailed,
    NotAnchoredYet,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.forms import AuditFilterForm, GrantForm, GrantRevokeForm, RecordFilterForm
from sharing.models import Record, Verdict
from sharing.selectors import (
    grant_list_given,
    grant_list_made_with,
    grant_list_received,
    owners_granting,
    record_list_filtered,
    record_list_owned,
    record_list_shared_with,
)
from sharing.services import grant_create, grant_revoke, grants_revoke_made_with, owner_resolve
from sharing.verification import OpenedRecord, record_open

RECORDS_PER_PAGE = 25
AUDIT_ENTRIES_PER_PAGE = 50
# Poses on a trajectory plot: the record and the ones before it on its topic, each one
# integrity-checked like any other view.
TRAJECTORY_POINTS = 20
# What a trajectory counts against PAGE_RATE_CONTENT, in single record checks: its poses are
# checked in one batched run (one task, one block, one access check per owner), so it costs
# the worker less than TRAJECTORY_POINTS single views but more than one.
TRAJECTORY_COST = 5
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
    form = RecordFilterForm(request.GET or None, records=records, with_owner=shared)
    filtered = record_list_filtered(records, **form.filters())
    page = Paginator(filtered, RECORDS_PER_PAGE).get_page(request.GET.get("page"))
    context = {
        "form": form,
        "page": page,
        "shared": shared,
        "total": records.count(),
        "granting": owners_granting(request.owner).select_related("user") if shared else None,
    }
    return render(request, "sharing/records.html", context)


# --- one record ----------------------------------------------------------------------------


@dataclass
class Refusal:
    """Why a record's content is not shown, and with which HTTP status."""

    outcome: str
    status: int
    message: str
    record: Record | None = None
    verdict: Verdict | None = None


def _open_or_refuse(
    request: HttpRequest, record_id: str, *, earlier: int = 0
) -> OpenedRecord | Refusal:
    try:
        return record_open(record_id=record_id, viewer=request.owner, earlier=earlier)
    except RecordNotFound as exc:
        return Refusal("not_found", 404, str(exc))
    except AccessDenied as exc:
        # Nothing of a record the viewer may not read is shown, not even its metadata.
        return Refusal(Verdict.Outcome.NO_ACCESS, 403, str(exc))
    except IntegrityCheckFailed as exc:
        return Refusal(Verdict.Outcome.TAMPERED, 409, str(exc), exc.record, exc.verdict)
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
        return no_store(
            render(request, "sharing/record_detail.html", context, status=opened.status)
        )
    record = opened.record
    context = {
        "record": record,
        "verdict": opened.verdict,
        "header": opened.header,
        "content": content_of(data_type=record.data_type, plaintext=opened.plaintext),
        "is_own": record.owner_id == request.owner.pk,
    }
    return no_store(render(request, "sharing/record_detail.html", context))


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


@owner_required
@page_throttle("content", cost=TRAJECTORY_COST)
@require_GET
def record_trajectory(request: HttpRequest, record_id: str) -> HttpResponse:
    """An SVG plot of the poses on an odometry record's topic, up to this record."""
    # Every earlier pose is checked against the chain too, in the same one check.
    opened = _open_or_refuse(request, str(record_id), earlier=TRAJECTORY_POINTS - 1)
    if isinstance(opened, Refusal):
        refused = HttpResponse(opened.message, status=opened.status, content_type="text/plain")
        return no_store(refused)
    if opened.record.data_type != ODOMETRY:
        raise Http404("only odometry records have a trajectory")
    results = [*opened.earlier, opened]
    passed = [result for result in results if not isinstance(result, SharingError)]
    plot = trajectory_plot([pose_of(result.plaintext) for result in passed])
    plot["refused"] = len(results) - len(passed)
    plot["topic"] = opened.record.topic
    response = render(request, "sharing/trajectory.svg", plot, content_type="image/svg+xml")
    return no_store(response)


def _download_name(record: Record) -> str:
    topic = re.sub(r"[^A-Za-z0-9_.-]+", "_", record.topic).strip("_") or "record"
    return f"{topic}-{record.seq}-{record.pk}.json"


# --- grants --------------------------------------------------------------------------------


@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def grants(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = GrantForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            grantee = owner_resolve(form.cleaned_data["grantee"])
            grant_create(owner=owner, grantee=grantee, made_with="session")
        except SharingError as exc:
            form.add_error("grantee", str(exc))
        else:
            messages.success(
                request,
                f"The grant to {grantee} is being written to the chain: {grantee} may read "
                "your records once it is confirmed there.",
            )
            return redirect("grants")
    context = {
        "form": form,
        "given": grant_list_given(owner),
        "received": grant_list_received(owner),
        "owner": owner,
    }
    return render(request, "sharing/grants.html", context, status=400 if form.is_bound else 200)


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
    if form.is_bound and not form.is_valid():
        return render(request, "sharing/audit.html", {"form": form, "owner": owner}, status=400)
    page = audit_page_of_owner(
        owner, page=request.GET.get("page"), per_page=AUDIT_ENTRIES_PER_PAGE, **form.filters()
    )
    context = {"form": form, "page": page, "owner": owner, "filtered": bool(form.filters())}
    return render(request, "sharing/audit.html", context)


# --- revoking an owner API token, and what it granted ----------------------------------------
# Here rather than in accounts: the page lists and revokes the grants the token made.


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def api_token_revoke(request: HttpRequest, token_id: int) -> HttpResponse:
    """GET: what revoking the token does, with the live grants it made; POST: revoke it, and
    those grants too unless the owner unticked them."""
    token = owner_token_of(request.owner, token_id)
    if token is None:
        raise Http404("no such API token")
    if request.method == "GET":
        context = {"token": token, "grants": list(grant_list_made_with(token))}
        return render(request, "accounts/api_token_revoke.html", context)
    was_live = token.revoked_at is None
    owner_token_revoke(token=token, actor=request.user)
    revoked = []
    if request.POST.get("revoke_grants") == "yes":
        revoked = grants_revoke_made_with(token=token)
    said = [f"The API token {token.name} {'is' if was_live else 'was already'} revoked."]
    if revoked:
        names = ", ".join(grant.grantee.username for grant in revoked)
        said.append(f"The access it gave {names} is revoked too; the chain follows.")
    messages.success(request, " ".join(said))
    return redirect("api-tokens")
