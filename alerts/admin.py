"""Admin console for owners' alerts: preferences, webhook endpoints, alerts, their deliveries
and the conditions that raise them.

Read-only like accounts.admin: the owner sets preferences and endpoints on their alerts page,
the worker raises and delivers alerts. A webhook's wrapped secret is never shown.
"""

from django.contrib import admin

from accounts.admin import ReadOnlyAdmin, shown_fields
from alerts.models import Alert, AlertCondition, AlertDelivery, AlertPreferences, WebhookEndpoint


@admin.register(AlertPreferences)
class AlertPreferencesAdmin(ReadOnlyAdmin):
    list_display = ("owner", "email", "email_verified_at", "robot_silent_minutes", "updated_at")
    search_fields = ("owner__user__username", "email")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(AlertPreferences)


@admin.register(WebhookEndpoint)
class WebhookEndpointAdmin(ReadOnlyAdmin):
    list_display = ("owner", "url", "secret_prefix", "created_at")
    search_fields = ("owner__user__username", "url")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(WebhookEndpoint, hidden=("secret_wrapped",))


@admin.register(Alert)
class AlertAdmin(ReadOnlyAdmin):
    list_display = ("owner", "kind", "subject", "created_at")
    list_filter = ("kind", "created_at")
    search_fields = ("owner__user__username", "subject", "summary")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(Alert)


@admin.register(AlertDelivery)
class AlertDeliveryAdmin(ReadOnlyAdmin):
    list_display = ("alert", "channel", "status", "attempts", "response_status", "sent_at")
    list_filter = ("channel", "status", "created_at")
    search_fields = ("alert__owner__user__username", "target")
    list_select_related = ("alert__owner__user",)
    fields = readonly_fields = shown_fields(AlertDelivery)


@admin.register(AlertCondition)
class AlertConditionAdmin(ReadOnlyAdmin):
    list_display = ("owner", "kind", "subject", "started_at", "resolved_at")
    list_filter = ("kind", ("resolved_at", admin.EmptyFieldListFilter))
    search_fields = ("owner__user__username", "subject")
    list_select_related = ("owner__user",)
    fields = readonly_fields = shown_fields(AlertCondition)
