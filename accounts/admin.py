"""Admin console for owners, their keys, robots, pairings, API tokens and funding, users,
account events, and the fingerprint of the portal's KEK.

Rows are made by the services (they create EOAs, wrap keys, queue chain work), so the admin
only reads them; secrets (wrapped keys, token hashes) are never shown. The operator is not
the owner: an owner's account can be deactivated or reactivated here, never given a password,
staff status or permissions, and every operator action on an owner's rows is shown to the
owner on their security page (AccountEvent).
"""

from django import forms
from django.contrib import admin, messages
from django.contrib.admin.utils import unquote
from django.contrib.auth import admin as auth_admin
from django.contrib.auth import get_user_model
from django.contrib.auth.base_user import AbstractBaseUser
from django.core.exceptions import PermissionDenied
from django.db.models import Model, QuerySet
from django.http import HttpRequest, HttpResponse

from accounts.events import account_event_record
from accounts.models import (
    AccountEvent,
    ChainActivity,
    EoaFunding,
    Owner,
    OwnerKey,
    OwnerToken,
    Robot,
    RobotPairing,
    SecretFingerprint,
)
from accounts.services.owners import owner_active_set, owner_approve, owner_refuse
from accounts.services.robots import robot_token_revoke


def shown_fields(model: type[Model], *, hidden: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The model's fields for a read-only page: all of them but `hidden` (secrets: wrapped keys,
    hashes of tokens and secrets, a robot's sealed token)."""
    return tuple(field.name for field in model._meta.fields if field.name not in hidden)


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
    list_display = (
        "username",
        "eoa_address",
        "approval",
        "chain_state",
        "registered_block",
        "created_at",
    )
    list_filter = ("approval", "chain_state", "created_at")
    search_fields = ("user__username", "eoa_address", "fund_tx", "enroll_tx", "register_tx")
    list_select_related = ("user",)
    fields = (
        "user",
        "eoa_address",
        "approval",
        "approved_by",
        "approved_at",
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
    actions = ("approve_signups", "refuse_signups")

    @admin.display(ordering="user__username")
    def username(self, owner: Owner) -> str:
        return owner.username

    # Sign-ups awaiting approval (SIGNUP_APPROVAL): the services queue the chain work or
    # deactivate the account, and tell the owner.

    @admin.action(description="Approve selected sign-ups", permissions=["approve"])
    def approve_signups(self, request: HttpRequest, queryset: QuerySet[Owner]) -> None:
        done = [owner_approve(owner=owner, operator=request.user) for owner in queryset]
        self._report_approvals(request, "Approved", done)

    @admin.action(description="Refuse selected sign-ups", permissions=["approve"])
    def refuse_signups(self, request: HttpRequest, queryset: QuerySet[Owner]) -> None:
        done = [owner_refuse(owner=owner, operator=request.user) for owner in queryset]
        self._report_approvals(request, "Refused", done)

    def _report_approvals(self, request: HttpRequest, verb: str, done: list[bool]) -> None:
        skipped = done.count(False)
        text = f"{verb} {done.count(True)} sign-up(s)."
        if skipped:
            text += f" {skipped} selected owner(s) were not awaiting approval: left as they are."
        self.message_user(request, text, messages.WARNING if skipped else messages.SUCCESS)

    def has_approve_permission(self, request: HttpRequest) -> bool:
        return request.user.has_perm("accounts.change_owner")


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
            robot_token_revoke(robot=robot, actor=request.user)
            count += 1
        self.message_user(request, f"Revoked {count} robot token(s).", messages.SUCCESS)

    def has_change_permission(self, request: HttpRequest, obj: object = None) -> bool:
        # Actions need change permission; every field stays read-only.
        return request.user.has_perm("accounts.change_robot")


# --- users: the operator is not the owner -----------------------------------------------------


def admin_action_record(
    request: HttpRequest, *, owner_id: int, action: str, detail: dict[str, object]
) -> None:
    """Tell the owner, on their security page, what an operator did to their rows."""
    account_event_record(
        owner=Owner.objects.get(pk=owner_id),
        kind=AccountEvent.Kind.ADMIN_ACTION,
        actor=request.user,
        detail={"action": action, **detail},
    )


def is_owner_account(user: AbstractBaseUser) -> bool:
    """Whether the user is an owner (the reverse one-to-one, cached once fetched)."""
    try:
        user.owner  # noqa: B018
    except Owner.DoesNotExist:
        return False
    return True


class OwnerAccountFilter(admin.SimpleListFilter):
    title = "account"
    parameter_name = "owner"

    def lookups(self, request: HttpRequest, model_admin: admin.ModelAdmin) -> list:
        return [("yes", "owners"), ("no", "operators and others")]

    def queryset(self, request: HttpRequest, queryset: QuerySet) -> QuerySet:
        if self.value() == "yes":
            return queryset.filter(owner__isnull=False)
        if self.value() == "no":
            return queryset.filter(owner__isnull=True)
        return queryset


class OwnerUserForm(forms.ModelForm):
    """What an operator may change on an owner's account: whether it may sign in. No
    password, staff status, permissions or groups (no declared password field either)."""

    class Meta:
        model = get_user_model()
        fields = ("is_active",)


admin.site.unregister(get_user_model())


@admin.register(get_user_model())
class UserAdmin(auth_admin.UserAdmin):
    """Django's user admin for operators' accounts; owners' accounts are only deactivated or
    reactivated here, never given a password, staff status or permissions, never deleted."""

    list_display = ("username", "is_owner", "is_active", "is_staff", "last_login")
    list_filter = (OwnerAccountFilter, "is_staff", "is_superuser", "is_active")
    owner_fieldsets = (
        (None, {"fields": ("username",)}),
        ("Personal info", {"fields": ("first_name", "last_name", "email")}),
        (
            "Access",
            {
                "fields": ("is_active",),
                "description": (
                    "This is an owner's account: its password, staff status and permissions "
                    "are not managed here. Deactivating or reactivating it is shown to the "
                    "owner on their security page."
                ),
            },
        ),
        ("Important dates", {"fields": ("last_login", "date_joined")}),
    )
    owner_readonly_fields = (
        "username",
        "first_name",
        "last_name",
        "email",
        "last_login",
        "date_joined",
    )

    @admin.display(boolean=True, description="owner")
    def is_owner(self, user: AbstractBaseUser) -> bool:
        return is_owner_account(user)

    def get_queryset(self, request: HttpRequest) -> QuerySet:
        return super().get_queryset(request).select_related("owner")

    def get_fieldsets(self, request: HttpRequest, obj: AbstractBaseUser | None = None) -> tuple:
        if obj is not None and is_owner_account(obj):
            return self.owner_fieldsets
        return super().get_fieldsets(request, obj)

    def get_readonly_fields(
        self, request: HttpRequest, obj: AbstractBaseUser | None = None
    ) -> tuple:
        if obj is not None and is_owner_account(obj):
            return self.owner_readonly_fields
        return super().get_readonly_fields(request, obj)

    def get_form(
        self, request: HttpRequest, obj: AbstractBaseUser | None = None, **kwargs: object
    ) -> type[forms.ModelForm]:
        if obj is not None and is_owner_account(obj):
            kwargs["form"] = OwnerUserForm
        return super().get_form(request, obj, **kwargs)

    def save_model(
        self, request: HttpRequest, obj: AbstractBaseUser, form: forms.ModelForm, change: bool
    ) -> None:
        if not (change and is_owner_account(obj)):
            super().save_model(request, obj, form, change)
            return
        # Only is_active is in the form; the service writes it and the owner's event.
        active = form.cleaned_data["is_active"]
        owner_active_set(owner=obj.owner, active=active, actor=request.user)

    def has_delete_permission(
        self, request: HttpRequest, obj: AbstractBaseUser | None = None
    ) -> bool:
        if obj is not None and is_owner_account(obj):
            return False
        return super().has_delete_permission(request, obj)

    def user_change_password(
        self, request: HttpRequest, id: str, form_url: str = ""
    ) -> HttpResponse:
        user = self.get_object(request, unquote(id))
        if user is not None and is_owner_account(user):
            # Setting an owner's password would let the operator sign in as the owner.
            if request.method == "POST":
                # A refused attempt is still worth the owner's knowing.
                admin_action_record(
                    request,
                    owner_id=user.owner.pk,
                    action="tried to set your password (refused)",
                    detail={},
                )
            raise PermissionDenied
        return super().user_change_password(request, id, form_url)


@admin.register(AccountEvent)
class AccountEventAdmin(ReadOnlyAdmin):
    list_display = ("owner", "kind", "actor", "created_at")
    list_filter = ("kind", "created_at")
    search_fields = ("owner__user__username", "actor__username")
    list_select_related = ("owner__user", "actor")
    readonly_fields = [f.name for f in AccountEvent._meta.fields]


@admin.register(ChainActivity)
class ChainActivityAdmin(ReadOnlyAdmin):
    """The index of owners' transactions the audit pages read, as the worker wrote it."""

    list_display = ("at", "owner", "kind", "record_count", "block_number", "tx_hash", "counterpart")
    list_filter = ("kind", "at")
    date_hierarchy = "at"
    search_fields = ("owner__user__username", "tx_hash")
    list_select_related = ("owner__user", "counterpart__user")
    readonly_fields = [f.name for f in ChainActivity._meta.fields]


@admin.register(RobotPairing)
class RobotPairingAdmin(ReadOnlyAdmin):
    """Pairing requests; the secret's hash and the token sealed for the robot are not shown."""

    list_display = ("code", "name", "state", "owner", "robot", "created_at", "expires_at")
    list_filter = ("state", "created_at")
    search_fields = ("code", "name", "owner__user__username")
    list_select_related = ("owner__user", "robot")
    fields = readonly_fields = shown_fields(RobotPairing, hidden=("secret_hash", "token_sm2"))


@admin.register(OwnerToken)
class OwnerTokenAdmin(ReadOnlyAdmin):
    """Owners' API tokens: names, prefixes, scopes and dates; never the hash. Revoking one is
    the owner's (its page offers to take back the grants it made)."""

    list_display = ("name", "owner", "token_prefix", "expires_at", "last_used_at", "revoked_at")
    list_filter = (("revoked_at", admin.EmptyFieldListFilter), "created_at")
    search_fields = ("name", "token_prefix", "owner__user__username")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(OwnerToken, hidden=("token_hash",))


@admin.register(EoaFunding)
class EoaFundingAdmin(ReadOnlyAdmin):
    list_display = ("owner", "amount_wei", "reason", "tx_hash", "created_at")
    list_filter = ("reason", "created_at")
    search_fields = ("owner__user__username", "tx_hash")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(EoaFunding)


@admin.register(SecretFingerprint)
class SecretFingerprintAdmin(ReadOnlyAdmin):
    """The KEK's fingerprint: changing it here would let a portal with another KEK serve."""

    list_display = ("name", "fingerprint", "created_at")
    fields = readonly_fields = shown_fields(SecretFingerprint)
