"""The owner's alerts page: which events go by e-mail and which to webhooks, the webhook
endpoints (each secret shown once), and the log of deliveries."""

import uuid

from django.conf import settings
from django.contrib import messages
from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import redirect, render
from django.urls import reverse
from django.views.decorators.cache import never_cache
from django.views.decorators.http import require_GET, require_http_methods, require_POST

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.models import Owner
from alerts.errors import AlertError
from alerts.forms import KIND_CHOICES, AlertPreferencesForm, WebhookEndpointForm
from alerts.models import AlertPreferences
from alerts.selectors import (
    alert_deliveries_of,
    alert_preferences_of,
    webhook_endpoint_of,
    webhook_endpoints_of,
)
from alerts.services import (
    WEI_PER_ETHER,
    alert_email_verify,
    alert_preferences_update,
    alert_test_send,
    webhook_endpoint_create,
    webhook_endpoint_delete,
)


def _page(
    request: HttpRequest,
    *,
    form: AlertPreferencesForm | None = None,
    webhook_form: WebhookEndpointForm | None = None,
    status: int = 200,
) -> HttpResponse:
    owner: Owner = request.owner
    if form is None:
        preferences = alert_preferences_of(owner)
        gas = preferences.gas_low_below_wei
        form = AlertPreferencesForm(
            initial={
                "email": preferences.email,
                "email_kinds": preferences.email_kinds,
                "webhook_kinds": preferences.webhook_kinds,
                "robot_silent_minutes": preferences.robot_silent_minutes,
                "gas_low_below_ether": None if gas is None else (gas / WEI_PER_ETHER).normalize(),
            }
        )
    context = {
        "form": form,
        "preferences": alert_preferences_of(owner),
        "kind_rows": _kind_rows(form),
        "webhook_form": webhook_form or WebhookEndpointForm(),
        "endpoints": webhook_endpoints_of(owner),
        "deliveries": alert_deliveries_of(owner),
    }
    preferences = context["preferences"]
    if not (preferences.email and preferences.email_verified_at) and not context["endpoints"]:
        context["no_channel"] = _no_channel(preferences)
    return render(request, "alerts/alerts.html", context, status=status)


def _kind_rows(form: AlertPreferencesForm) -> list[tuple[str, str, bool, bool]]:
    """(kind, label, by e-mail, to webhooks) for the page's table of checkboxes."""
    if form.is_bound:
        email, webhook = form.data.getlist("email_kinds"), form.data.getlist("webhook_kinds")
    else:
        email, webhook = form.initial["email_kinds"], form.initial["webhook_kinds"]
    return [(kind, label, kind in email, kind in webhook) for kind, label in KIND_CHOICES]


@never_cache
@owner_required
@page_throttle()
@require_http_methods(["GET", "POST"])
def alert_settings(request: HttpRequest) -> HttpResponse:
    if request.method == "GET":
        return _page(request)
    form = AlertPreferencesForm(request.POST)
    if form.is_valid():
        try:
            preferences = alert_preferences_update(
                owner=request.owner,
                email=form.cleaned_data["email"],
                email_kinds=form.cleaned_data["email_kinds"],
                webhook_kinds=form.cleaned_data["webhook_kinds"],
                robot_silent_minutes=form.cleaned_data["robot_silent_minutes"],
                gas_low_below_wei=form.gas_low_below_wei,
                verify_url=_verify_url(request),
            )
        except AlertError as exc:
            form.add_error(None, str(exc))
        else:
            saved = "Your alert settings are saved."
            if preferences.email and preferences.email_verified_at is None:
                saved += f" We sent a link to {preferences.email}: open it to get e-mail alerts."
            messages.success(request, saved)
            return redirect("alerts")
    return _page(request, form=form, status=400)


def _verify_url(request: HttpRequest) -> str:
    """Where the e-mail's link points, its token appended: the portal's public URL if set (a
    proxy may pass another host), else the host this request came to."""
    path = reverse("alerts") + "verify/"
    if settings.ALERTS_PORTAL_URL:
        return settings.ALERTS_PORTAL_URL.rstrip("/") + path
    return request.build_absolute_uri(path)


@never_cache
@owner_required
@page_throttle()
@require_GET
def email_verify(request: HttpRequest, token: str) -> HttpResponse:
    try:
        preferences = alert_email_verify(owner=request.owner, token=token)
    except AlertError as exc:
        messages.error(request, f"Your address is not confirmed: {exc}.")
    else:
        messages.success(request, f"{preferences.email} is confirmed: e-mail alerts go there.")
    return redirect("alerts")


@never_cache
@owner_required
@page_throttle()
@require_POST
def webhook_create(request: HttpRequest) -> HttpResponse:
    form = WebhookEndpointForm(request.POST)
    if form.is_valid():
        try:
            endpoint, secret = webhook_endpoint_create(
                owner=request.owner, url=form.cleaned_data["url"]
            )
        except AlertError as exc:
            form.add_error("url", str(exc))
        else:
            # The secret exists only in this response: it is kept wrapped and never shown again.
            context = {"endpoint": endpoint, "secret": secret}
            return no_store(render(request, "alerts/webhook_created.html", context, status=201))
    return _page(request, webhook_form=form, status=400)


@owner_required
@page_throttle()
@require_POST
def webhook_delete(request: HttpRequest, endpoint_id: uuid.UUID) -> HttpResponse:
    endpoint = webhook_endpoint_of(request.owner, endpoint_id)
    if endpoint is None:
        raise Http404("no such webhook")
    webhook_endpoint_delete(endpoint=endpoint)
    messages.success(request, f"The webhook {endpoint.url} was deleted.")
    return redirect("alerts")


@owner_required
@page_throttle()
@require_POST
def alert_test(request: HttpRequest) -> HttpResponse:
    alert = alert_test_send(owner=request.owner)
    count = alert.deliveries.count()
    if count:
        channels = "1 channel" if count == 1 else f"{count} channels"
        messages.success(request, f"A test alert is on its way to {channels}.")
    else:
        messages.warning(
            request, f"Nothing was sent: {_no_channel(alert_preferences_of(request.owner))}"
        )
    return redirect("alerts")


def _no_channel(preferences: AlertPreferences) -> str:
    """Why a test alert has nowhere to go, in words the owner can act on."""
    if preferences.email and preferences.email_verified_at is None:
        return (
            f"{preferences.email} is not confirmed yet (follow the link sent to it) and no "
            "webhook is set up."
        )
    return "no e-mail address and no webhook is set up to receive alerts; add one above."
