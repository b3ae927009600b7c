"""Admin console for records, their anchored roots, grants and their changes, the access log,
verdicts, security events and exports.

Read-only like accounts.admin; the two actions repair anchoring and re-run the integrity
check, and each tells the owners concerned on their security page. Envelope bytes and keys
are never shown, and nothing here decrypts.
"""

import uuid
from collections import Counter, defaultdict
from collections.abc import Iterable

from django.contrib import admin, messages
from django.db.models import QuerySet
from django.http import HttpRequest

from accounts.admin import ReadOnlyAdmin, admin_action_record, shown_fields
from accounts.errors import IdentityMismatch
from chainworker.errors import ChainError
from sharing.models import (
    Access,
    AnchorRoot,
    Export,
    ExportRecord,
    Grant,
    GrantChange,
    Record,
    SecurityEvent,
    Verdict,
)
from sharing.services.anchoring import records_reanchor
from sharing.verification.check import records_verify

# Re-verification runs in the admin's request: keep a selection small enough to answer.
REVERIFY_MAX = 200


class TamperedFilter(admin.SimpleListFilter):
    title = "integrity"
    parameter_name = "tampered"

    def lookups(self, request: HttpRequest, model_admin: admin.ModelAdmin) -> list:
        return [("yes", "tampered"), ("no", "never failed a check")]

    def queryset(self, request: HttpRequest, queryset: QuerySet[Record]) -> QuerySet[Record]:
        if self.value() == "yes":
            return queryset.filter(tampered_at__isnull=False)
        if self.value() == "no":
            return queryset.filter(tampered_at__isnull=True)
        return queryset


@admin.register(Record)
class RecordAdmin(ReadOnlyAdmin):
    list_display = (
        "id",
        "owner",
        "topic",
        "data_type",
        "seq",
        "captured_at",
        "status",
        "block_number",
        "anchor_attempts",
        "tampered",
    )
    list_filter = ("status", TamperedFilter, "deletion_reason", "data_type", "captured_at")
    search_fields = ("id", "topic", "digest", "tx_hash", "owner__user__username", "robot__name")
    list_select_related = ("owner__user",)
    date_hierarchy = "captured_at"
    fields = (
        "id",
        "owner",
        "robot",
        "topic",
        "data_type",
        "seq",
        "captured_at",
        "key_id",
        "digest",
        "size",
        "status",
        "tx_hash",
        "block_number",
        "anchored_at",
        "anchor_attempts",
        "failure_reason",
        "tampered_at",
        "created_at",
        "deleted_at",
        "deleted_by",
        "deletion_reason",
        "purged_at",
    )
    readonly_fields = fields
    actions = ("reanchor_failed", "reverify")

    @admin.display(boolean=True, ordering="tampered_at")
    def tampered(self, record: Record) -> bool:
        return record.tampered_at is not None

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        # The actions need change permission; every field stays read-only.
        return request.user.has_perm("sharing.change_record")

    @admin.action(description="Re-anchor the selected failed records", permissions=["change"])
    def reanchor_failed(self, request: HttpRequest, queryset: QuerySet[Record]) -> None:
        failed = queryset.filter(status=Record.Status.FAILED)
        by_owner = _ids_by_owner(failed.values_list("owner_id", "pk"))
        count = records_reanchor(record_ids=list(queryset.values_list("pk", flat=True)))
        for owner_id, record_ids in by_owner.items():
            admin_action_record(
                request,
                owner_id=owner_id,
                action="re-anchored failed records",
                detail={"records": record_ids},
            )
        skipped = queryset.count() - count
        note = f"; {skipped} selected record(s) had not failed: left alone" if skipped else ""
        self.message_user(
            request,
            f"{count} failed record(s) are pending again and their anchoring is queued{note}.",
            messages.SUCCESS if count else messages.WARNING,
        )

    @admin.action(
        description="Re-verify the selected records against the chain", permissions=["change"]
    )
    def reverify(self, request: HttpRequest, queryset: QuerySet[Record]) -> None:
        records = list(queryset.order_by("captured_at")[: REVERIFY_MAX + 1])
        if len(records) > REVERIFY_MAX:
            self.message_user(
                request,
                f"Select at most {REVERIFY_MAX} records to re-verify at once.",
                messages.ERROR,
            )
            return
        outcomes: Counter[str] = Counter()
        tampered = []
        checked: list[Record] = []
        # One check per owner (with that owner's rights), all the owner's records at once.
        for owner_id, owned in _records_by_owner(records).items():
            try:
                verifications = records_verify(
                    record_ids=[record.pk for record in owned],
                    viewer_id=owner_id,
                    checked_by_id=request.user.pk,
                )
            except ChainError as exc:
                self.message_user(
                    request,
                    f"The chain is unavailable ({exc}); {sum(outcomes.values())} record(s) "
                    "were checked before it failed.",
                    messages.ERROR,
                )
                break
            except IdentityMismatch as exc:
                # The owner's commitment on chain differs: an account event is written.
                ids = ", ".join(str(record.pk) for record in owned)
                self.message_user(request, f"Records {ids}: {exc}", messages.ERROR)
                continue
            checked += owned
            for verification in verifications:
                outcomes[verification.verdict.outcome] += 1
                if verification.verdict.outcome == Verdict.Outcome.TAMPERED:
                    tampered.append(str(verification.verdict.record_id))
        # Only verdicts are kept and shown: the envelope checked is never opened here.
        for owner_id, record_ids in _ids_by_owner((r.owner_id, r.pk) for r in checked).items():
            admin_action_record(
                request,
                owner_id=owner_id,
                action="re-verified records against the chain",
                detail={"records": record_ids},
            )
        labels = dict(Verdict.Outcome.choices)
        if outcomes:
            summary = ", ".join(f"{count} {labels[outcome]}" for outcome, count in outcomes.items())
            level = messages.ERROR if tampered else messages.SUCCESS
            self.message_user(
                request,
                f"Re-verified with their owners' rights, recorded as your checks: {summary}.",
                level,
            )
        if tampered:
            self.message_user(request, f"TAMPERED: {', '.join(tampered)}", messages.ERROR)


def _records_by_owner(records: Iterable[Record]) -> dict[int, list[Record]]:
    grouped: dict[int, list[Record]] = defaultdict(list)
    for record in records:
        grouped[record.owner_id].append(record)
    return grouped


def _ids_by_owner(pairs: Iterable[tuple[int, uuid.UUID]]) -> dict[int, list[str]]:
    """Record ids grouped by owner, for one event per owner."""
    grouped: dict[int, list[str]] = defaultdict(list)
    for owner_id, record_id in pairs:
        grouped[owner_id].append(str(record_id))
    return dict(grouped)


@admin.register(Grant)
class GrantAdmin(ReadOnlyAdmin):
    list_display = (
        "owner",
        "grantee",
        "status",
        "grant_block",
        "revoke_block",
        "created_at",
        "updated_at",
    )
    list_filter = ("status", "created_at")
    search_fields = (
        "owner__user__username",
        "grantee__user__username",
        "owner__eoa_address",
        "grantee__eoa_address",
        "grant_tx",
        "revoke_tx",
    )
    list_select_related = ("owner__user", "grantee__user")
    readonly_fields = [f.name for f in Grant._meta.fields]


@admin.register(Access)
class AccessAdmin(ReadOnlyAdmin):
    """The access log's lines (a page, a plot, an export...); their verdicts point to them."""

    list_display = ("created_at", "kind", "count", "viewer", "record_owner", "credential")
    list_filter = ("kind", "credential", "created_at")
    search_fields = ("viewer__user__username", "record_owner__user__username", "topic")
    list_select_related = ("viewer__user", "record_owner__user")
    readonly_fields = [f.name for f in Access._meta.fields]


@admin.register(Verdict)
class VerdictAdmin(ReadOnlyAdmin):
    list_display = ("record", "access", "outcome", "source", "block_number", "created_at")
    list_filter = (
        "outcome",
        "access__credential",
        "source",
        ("access__checked_by", admin.EmptyFieldListFilter),
        "created_at",
    )
    search_fields = (
        "record__id",
        "access__viewer__user__username",
        "computed_digest",
        "chain_digest",
    )
    list_select_related = (
        "record__owner__user",
        "access__viewer__user",
        "access__checked_by",
    )
    readonly_fields = [f.name for f in Verdict._meta.fields]


@admin.register(SecurityEvent)
class SecurityEventAdmin(ReadOnlyAdmin):
    list_display = ("kind", "record", "owner", "created_at")
    list_filter = ("kind", "created_at")
    search_fields = ("record__id", "owner__user__username")
    list_select_related = ("record__owner__user", "owner__user")
    readonly_fields = [f.name for f in SecurityEvent._meta.fields]


@admin.register(AnchorRoot)
class AnchorRootAdmin(ReadOnlyAdmin):
    """The Merkle roots records are anchored under (the leaves' bytes are not shown)."""

    list_display = ("id", "owner", "size", "status", "block_number", "anchored_at", "created_at")
    list_filter = ("status", "created_at")
    search_fields = ("root", "prev_root", "tx_hash", "sender", "owner__user__username")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(AnchorRoot, hidden=("leaves",))


@admin.register(GrantChange)
class GrantChangeAdmin(ReadOnlyAdmin):
    """Each grant's history: made, terms changed, revoked, with the credential that did it."""

    list_display = ("grant", "kind", "made_with", "token", "created_at")
    list_filter = ("kind", "made_with", "created_at")
    search_fields = ("grant__owner__user__username", "grant__grantee__user__username")
    list_select_related = ("grant__owner__user", "grant__grantee__user", "token")
    fields = readonly_fields = shown_fields(GrantChange)


@admin.register(Export)
class ExportAdmin(ReadOnlyAdmin):
    """Exports' progress and files' names and sizes; the export's wrapped key is not shown."""

    list_display = ("id", "requester", "status", "total", "exported", "created_at", "expires_at")
    list_filter = ("status", "credential", "created_at")
    search_fields = ("id", "requester__user__username", "mcap_sm3")
    list_select_related = ("requester__user",)
    fields = readonly_fields = shown_fields(Export, hidden=("key_wrapped",))


@admin.register(ExportRecord)
class ExportRecordAdmin(ReadOnlyAdmin):
    """Which records an export holds."""

    list_display = ("export", "record")
    search_fields = ("export__id", "record__id")
    list_select_related = ("export", "record")
    fields = readonly_fields = shown_fields(ExportRecord)
