"""Owner pages of the sharing app: my data, shared with me, a record, grants, audit.

A record's content is only ever shown through `record_open`: the worker checks access and
the stored ciphertext's SM3 digest against the chain, and the content is decrypted only
when the verdict is `verified`. The verdict is shown first, with its HTTP status.
"""

import base64
import binascii
import json
import math
import re
from dataclasses import dataclass, field
from typing import Any

from django.contrib import messages
from django.core.paginator import Paginator
from django.db.models import QuerySet
from django.http import Http404, HttpRequest, HttpResponse, JsonResponse
from django.shortcuts import redirect, render
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.models import Owner
from accounts.views import no_store, owner_required
from chainworker.chain import ChainError, ChainEvent, bytes32_to_record_id
from sharing.errors import (
    AccessDenied,
    IntegrityCheckFailed,
    NotAnchoredYet,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.forms import GrantForm, GrantRevokeForm, RecordFilterForm
from sharing.models import Record, Verdict
from sharing.selectors import (
    chain_events_of_owner,
    grant_list_given,
    grant_list_received,
    owners_by_address,
    owners_granting,
    record_get_visible,
    record_list_owned,
    record_list_shared_with,
    record_topic_history,
    verdict_latest,
)
from sharing.services import (
    OpenedRecord,
    grant_create,
    grant_revoke,
    owner_resolve,
    record_open,
    record_open_many,
)

RECORDS_PER_PAGE = 25
AUDIT_ENTRIES_PER_PAGE = 50
# Record ids listed under one upload transaction on the audit page; the rest are counted.
AUDIT_RECORDS_PER_UPLOAD = 10
# Poses on a trajectory plot: the record and the ones before it on its topic, each one
# integrity-checked like any other view.
TRAJECTORY_POINTS = 20
ODOMETRY = "nav_msgs/Odometry"
IMAGE_TYPES = {"sensor_msgs/Image", "sensor_msgs/CompressedImage"}
MISSING = "-"
# A record page's refusal for a record whose anchoring failed (the worker's verdict says only
# "not anchored yet").
ANCHORING_FAILED = "anchoring_failed"
_IMAGE_MAGIC = {b"\x89PNG\r\n\x1a\n": "image/png", b"\xff\xd8\xff": "image/jpeg"}


# --- record lists --------------------------------------------------------------------------


@owner_required
@require_GET
def my_records(request: HttpRequest) -> HttpResponse:
    return _record_list(request, record_list_owned(request.owner), shared=False)


@owner_required
@require_GET
def shared_records(request: HttpRequest) -> HttpResponse:
    return _record_list(request, record_list_shared_with(request.owner), shared=True)


def _record_list(request: HttpRequest, records: QuerySet[Record], *, shared: bool) -> HttpResponse:
    form = RecordFilterForm(request.GET or None, records=records, with_owner=shared)
    filtered = form.filter(records) if form.is_bound else records
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


def _open_or_refuse(request: HttpRequest, record_id: str) -> OpenedRecord | Refusal:
    viewer: Owner = request.owner
    try:
        return record_open(record_id=record_id, viewer=viewer)
    except RecordNotFound as exc:
        return Refusal("not_found", 404, str(exc))
    except AccessDenied as exc:
        return Refusal(Verdict.Outcome.NO_ACCESS, 403, str(exc))
    except IntegrityCheckFailed as exc:
        record = record_get_visible(viewer, record_id)
        verdict = verdict_latest(record, viewer) if record else None
        return Refusal(Verdict.Outcome.TAMPERED, 409, str(exc), record, verdict)
    except NotAnchoredYet as exc:
        record = record_get_visible(viewer, record_id)
        verdict = verdict_latest(record, viewer) if record else None
        if record is not None and record.status == Record.Status.FAILED:
            # Not worth waiting for: it stays unanchored until an operator anchors it again.
            message = f"anchoring this record failed: {record.failure_reason or 'no reason given'}"
            return Refusal(ANCHORING_FAILED, 409, message, record, verdict)
        return Refusal(Verdict.Outcome.NOT_ANCHORED_YET, 409, str(exc), record, verdict)
    except VerificationUnavailable as exc:
        return Refusal("unavailable", 503, str(exc))


@owner_required
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
        "content": _content(opened),
        "is_own": record.owner_id == request.owner.pk,
    }
    return no_store(render(request, "sharing/record_detail.html", context))


@owner_required
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
@require_GET
def record_trajectory(request: HttpRequest, record_id: str) -> HttpResponse:
    """An SVG plot of the poses on an odometry record's topic, up to this record."""
    opened = _open_or_refuse(request, str(record_id))
    if isinstance(opened, Refusal):
        refused = HttpResponse(opened.message, status=opened.status, content_type="text/plain")
        return no_store(refused)
    if opened.record.data_type != ODOMETRY:
        raise Http404("only odometry records have a trajectory")
    history = record_topic_history(opened.record, limit=TRAJECTORY_POINTS)
    earlier = [record for record in history if record.pk != opened.record.pk]
    # Every earlier pose is checked against the chain too, all checks queued at once.
    results = [*record_open_many(records=earlier, viewer=request.owner), opened]
    poses, refused = [], 0
    for result in results:
        if isinstance(result, SharingError):
            refused += 1
            continue
        pose = _pose(_document(result.plaintext))
        if pose is not None:
            poses.append(pose)
    plot = _trajectory_plot(poses)
    plot["refused"] = refused
    plot["topic"] = opened.record.topic
    response = render(request, "sharing/trajectory.svg", plot, content_type="image/svg+xml")
    return no_store(response)


def _download_name(record: Record) -> str:
    topic = re.sub(r"[^A-Za-z0-9_.-]+", "_", record.topic).strip("_") or "record"
    return f"{topic}-{record.seq}-{record.pk}.json"


def _document(plaintext: bytes) -> Any:
    try:
        return json.loads(plaintext)
    except (ValueError, UnicodeDecodeError):
        return None


@dataclass
class Content:
    """What the record page shows of a decrypted record."""

    document: Any = None
    pretty: str = ""
    size: int = 0
    image_url: str = ""
    image_size: tuple[int | None, int | None] = (None, None)
    odometry: list[tuple[str, str]] = field(default_factory=list)
    is_odometry: bool = False


def _content(opened: OpenedRecord) -> Content:
    content = Content(size=len(opened.plaintext))
    document = _document(opened.plaintext)
    if document is None:
        content.pretty = "(not JSON: download the raw record)"
        return content
    content.document = document
    data = document.get("K") if isinstance(document, dict) else None
    data_type = opened.record.data_type
    shown = document
    if data_type in IMAGE_TYPES and isinstance(data, dict):
        content.image_url = _image_data_url(data.get("data"))
        content.image_size = (data.get("width"), data.get("height"))
        if content.image_url:
            length = len(data.get("data", ""))
            shown = {**document, "K": {**data, "data": f"<{length} base64 characters, above>"}}
    if data_type == ODOMETRY and isinstance(data, dict):
        content.is_odometry = True
        content.odometry = _odometry_rows(data)
    content.pretty = json.dumps(shown, indent=2, ensure_ascii=False)
    return content


def _image_data_url(encoded: object) -> str:
    """A data: URL for a base64 PNG or JPEG; empty for anything else."""
    if not isinstance(encoded, str):
        return ""
    try:
        raw = base64.b64decode(encoded, validate=True)
    except (binascii.Error, ValueError):
        return ""
    for magic, mime in _IMAGE_MAGIC.items():
        if raw.startswith(magic):
            return f"data:{mime};base64,{encoded}"
    return ""


def _number(value: object, digits: int = 4) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return MISSING
    return f"{value:.{digits}f}"


def _vector(value: object, names: str = "xyz") -> str:
    if not isinstance(value, dict):
        return MISSING
    return ", ".join(f"{name} {_number(value.get(name))}" for name in names)


def _yaw(orientation: object) -> float | None:
    """Heading about z (radians) of a quaternion dict, or None."""
    if not isinstance(orientation, dict):
        return None
    try:
        x, y, z, w = (float(orientation[name]) for name in "xyzw")
    except (KeyError, TypeError, ValueError):
        return None
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def _odometry_rows(data: dict) -> list[tuple[str, str]]:
    header = data.get("header") if isinstance(data.get("header"), dict) else {}
    stamp = header.get("stamp") if isinstance(header.get("stamp"), dict) else {}
    yaw = _yaw(data.get("orientation"))
    child_frame = data.get("child_frame_id") or MISSING
    return [
        ("Stamp", str(stamp.get("iso", MISSING))),
        ("Frame", f"{header.get('frame_id') or MISSING} to {child_frame}"),
        ("Position (m)", _vector(data.get("position"))),
        ("Orientation (quaternion)", _vector(data.get("orientation"), "xyzw")),
        ("Heading (yaw)", MISSING if yaw is None else f"{math.degrees(yaw):.1f}°"),
        ("Linear velocity (m/s)", _vector(data.get("linear_velocity"))),
        ("Angular velocity (rad/s)", _vector(data.get("angular_velocity"))),
    ]


def _pose(document: Any) -> tuple[float, float, float | None] | None:
    """(x, y, yaw) of an odometry record, or None."""
    data = document.get("K") if isinstance(document, dict) else None
    position = data.get("position") if isinstance(data, dict) else None
    if not isinstance(position, dict):
        return None
    x, y = position.get("x"), position.get("y")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in (x, y)):
        return None
    return float(x), float(y), _yaw(data.get("orientation"))


def _trajectory_plot(poses: list[tuple[float, float, float | None]]) -> dict[str, object]:
    """Screen coordinates of the poses on a square-scaled plot (y up)."""
    width, height, margin = 480, 360, 36
    if not poses:
        return {"width": width, "height": height, "points": "", "count": 0}
    xs, ys = [p[0] for p in poses], [p[1] for p in poses]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 0.5)
    scale = min(width - 2 * margin, height - 2 * margin) / span
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2

    def screen(x: float, y: float) -> tuple[float, float]:
        return round(width / 2 + (x - cx) * scale, 1), round(height / 2 - (y - cy) * scale, 1)

    points = [screen(x, y) for x, y, _ in poses]
    last_x, last_y, yaw = poses[-1]
    end = points[-1]
    arrow = None
    if yaw is not None:
        arrow = (round(end[0] + 22 * math.cos(yaw), 1), round(end[1] - 22 * math.sin(yaw), 1))
    return {
        "width": width,
        "height": height,
        "points": " ".join(f"{x},{y}" for x, y in points),
        "start": points[0],
        "end": end,
        "arrow": arrow,
        "count": len(poses),
        "x_range": f"{min(xs):.2f} … {max(xs):.2f}",
        "y_range": f"{min(ys):.2f} … {max(ys):.2f}",
        "last": f"{last_x:.2f}, {last_y:.2f}",
    }


# --- grants --------------------------------------------------------------------------------


@owner_required
@require_http_methods(["GET", "POST"])
def grants(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = GrantForm(request.POST or None)
    if request.method == "POST" and form.is_valid():
        try:
            grantee = owner_resolve(form.cleaned_data["grantee"])
            grant_create(owner=owner, grantee=grantee)
        except SharingError as exc:
            form.add_error("grantee", str(exc))
        else:
            messages.success(
                request,
                f"{grantee} may now read your records. The grant is being written to the chain.",
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


@dataclass
class AuditEntry:
    block_number: int
    tx_hash: str
    kind: str
    title: str
    detail: str = ""
    records: list[tuple[str, Record | None]] = field(default_factory=list)
    more_records: int = 0


@owner_required
@require_GET
def audit(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    try:
        events = chain_events_of_owner(owner)
    except ChainError as exc:
        context = {"problem": f"The chain cannot be read right now: {exc}", "owner": owner}
        return render(request, "sharing/audit.html", context, status=503)
    entries = _audit_entries(owner, events)
    page = Paginator(entries, AUDIT_ENTRIES_PER_PAGE).get_page(request.GET.get("page"))
    return render(request, "sharing/audit.html", {"page": page, "owner": owner})


def _audit_entries(owner: Owner, events: list[ChainEvent]) -> list[AuditEntry]:
    """The owner's events, newest first; the uploads of one transaction are one entry."""
    names = owners_by_address(
        [str(e.args[arg]) for e in events for arg in ("owner", "grantee") if arg in e.args]
    )

    def who(address: object) -> str:
        found = names.get(str(address).lower())
        return found.username if found else str(address)

    me = owner.eoa_address.lower()
    entries: list[AuditEntry] = []
    uploads: dict[str, AuditEntry] = {}
    upload_ids: dict[str, list[str]] = {}
    for event in events:
        args = event.args
        if event.name == "DataUploaded":
            entry = uploads.get(event.tx_hash)
            if entry is None:
                entry = AuditEntry(event.block_number, event.tx_hash, "upload", "")
                uploads[event.tx_hash] = entry
                upload_ids[event.tx_hash] = []
                entries.append(entry)
            upload_ids[event.tx_hash].append(str(bytes32_to_record_id(args["id"])))
            continue
        entry = AuditEntry(event.block_number, event.tx_hash, event.name, "")
        if event.name == "Enrolled":
            entry.title = "Enrolled in the AuthROS contract by the portal operator"
        elif event.name == "Registered":
            entry.title = "Registered the key commitment"
            entry.detail = "0x" + bytes(args["commitment"]).hex()
        elif event.name == "KeyRotated":
            entry.title = "Rotated the key"
            entry.detail = (
                f"0x{bytes(args['oldCommitment']).hex()} → 0x{bytes(args['newCommitment']).hex()}"
            )
        elif event.name in ("AuthorityGranted", "AuthorityRevoked"):
            granted = event.name == "AuthorityGranted"
            if str(args["owner"]).lower() == me:
                verb = "Granted" if granted else "Revoked"
                entry.title = f"{verb} access to {who(args['grantee'])}"
                entry.kind = "grant-given" if granted else "revoke-given"
            else:
                verb = "granted you" if granted else "revoked your"
                entry.title = f"{who(args['owner'])} {verb} access"
                entry.kind = "grant-received" if granted else "revoke-received"
        entries.append(entry)
    known = {
        str(record.pk): record
        for record in Record.objects.filter(
            owner=owner, pk__in=[i for ids in upload_ids.values() for i in ids]
        )
    }
    for tx_hash, ids in upload_ids.items():
        entry = uploads[tx_hash]
        entry.title = f"Anchored {len(ids)} record{'s' if len(ids) != 1 else ''}"
        entry.records = [(i, known.get(i)) for i in ids[:AUDIT_RECORDS_PER_UPLOAD]]
        entry.more_records = max(len(ids) - AUDIT_RECORDS_PER_UPLOAD, 0)
    entries.reverse()
    return entries
