"""Admin console for owners, their keys and robots.

Rows are made by the services (they create EOAs, wrap keys, queue chain work), so the admin
only reads them; secrets (wrapped keys, token hashes) are never shown.
"""

from django.contrib import admin, messages
from django.db.models import QuerySet
from django.http import HttpRequest

from accounts.models import Owner, OwnerKey, Robot
from accounts.services import robot_token_revoke


class ReadOnlyAdmin(admin.ModelAdmin):
    """Every field read-only; rows come from the services, never from this console."""

    def has_add_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False

    def has_delete_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False


class OwnerKeyInline(admin.TabularInline):
    model = OwnerKey
    fields = ("key_id", "is_current", "chain_state", "tx_hash", "block_number", "created_at")
    readonly_fields = fields
    extra = 0
    can_delete = False
    show_change_link = True

    def has_add_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False


class RobotInline(admin.TabularInline):
    model = Robot
    fields = ("name", "token_prefix", "is_active", "last_seq", "created_at", "revoked_at")
    readonly_fields = fields
    extra = 0
    can_delete = False
    show_change_link = True

    def has_add_permission(self, request: HttpRequest, obj: object = None) -> bool:
        return False


@admin.register(Owner)
class OwnerAdmin(ReadOnlyAdmin):
    list_display = ("username", "eoa_address", "chain_state", "registered_block", "created_at")
    list_filter = ("chain_state", "created_at")
    search_fields = ("user__username", "eoa_address", "fund_tx", "enroll_tx", "register_tx")
    list_select_related = ("user",)
    fields = (
        "user",
        "eoa_address",
        "chain_state",
        "chain_error",
        "fund_tx",
        "enroll_tx",
        "register_tx",
        "registered_block",
        "created_at",
    )
    readonly_fields = fields
    inlines = (OwnerKeyInline, RobotInline)

    @admin.display(ordering="user__username")
    def username(self, owner: Owner) -> str:
        return owner.username


@admin.register(OwnerKey)
class OwnerKeyAdmin(ReadOnlyAdmin):
    list_display = ("key_id", "owner", "is_current", "chain_state", "block_number", "created_at")
    list_filter = ("is_current", "chain_state")
    search_fields = ("key_id", "owner__user__username", "commitment", "tx_hash")
    list_select_related = ("owner__user",)
    fields = (
        "owner",
        "key_id",
        "commitment",
        "is_current",
        "chain_state",
        "tx_hash",
        "block_number",
        "created_at",
        "retired_at",
    )
    readonly_fields = fields


@admin.register(Robot)
class RobotAdmin(ReadOnlyAdmin):
    list_display = ("name", "owner", "id", "token_prefix", "is_active", "last_seq", "created_at")
    list_filter = ("is_active", "created_at")
    search_fields = ("name", "id", "token_prefix", "owner__user__username")
    list_select_related = ("owner__user",)
    fields = (
        "id",
        "owner",
        "name",
        "token_prefix",
        "is_active",
        "last_seq",
        "created_at",
        "revoked_at",
    )
    readonly_fields = fields
    actions = ("revoke_tokens",)

    @admin.action(description="Revoke the tokens of the selected robots", permissions=["change"])
    def revoke_tokens(self, request: HttpRequest, queryset: QuerySet[Robot]) -> None:
        count = 0
        for robot in queryset.filter(is_active=True):
            robot_token_revoke(robot=robot)
            count += 1
        self.message_user(request, f"Revoked {count} robot token(s).", messages.SUCCESS)

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        # Actions need change permission; every field stays read-only.
        return request.user.has_perm("accounts.change_robot")
