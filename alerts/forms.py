"""Forms of the alerts page: the owner's choices and a new webhook endpoint."""

from decimal import Decimal

from django import forms

from alerts.models import AlertKind
from alerts.services import (
    CHOOSABLE_KINDS,
    ROBOT_SILENT_MINUTES_MAX,
    ROBOT_SILENT_MINUTES_MIN,
    WEI_PER_ETHER,
)

KIND_CHOICES = [(kind, AlertKind(kind).label) for kind in CHOOSABLE_KINDS]


class AlertPreferencesForm(forms.Form):
    email = forms.EmailField(
        required=False,
        max_length=254,
        label="E-mail address for alerts",
        widget=forms.EmailInput(attrs={"autocomplete": "email"}),
    )
    email_kinds = forms.MultipleChoiceField(
        choices=KIND_CHOICES,
        required=False,
        widget=forms.CheckboxSelectMultiple,
        label="Send by e-mail",
    )
    webhook_kinds = forms.MultipleChoiceField(
        choices=KIND_CHOICES,
        required=False,
        widget=forms.CheckboxSelectMultiple,
        label="Send to my webhooks",
    )
    robot_silent_minutes = forms.IntegerField(
        required=False,
        min_value=ROBOT_SILENT_MINUTES_MIN,
        max_value=ROBOT_SILENT_MINUTES_MAX,
        label="A robot is silent after (minutes)",
        help_text="A robot that sends nothing for this long is reported once, until it sends "
        "again. Empty: not watched.",
    )
    gas_low_below_ether = forms.DecimalField(
        required=False,
        min_value=Decimal("0.000000001"),
        max_value=Decimal(10**9),
        max_digits=28,
        decimal_places=18,
        label="Low on gas below (ETH)",
        help_text="Your account is reported once when its balance falls below this, until it "
        "is topped up again. Empty: not watched.",
    )

    def clean(self) -> dict:
        cleaned = super().clean()
        chosen = set(cleaned.get("email_kinds") or []) | set(cleaned.get("webhook_kinds") or [])
        needed = [
            ("email", bool(cleaned.get("email_kinds")), "Give an address for the e-mail alerts."),
            (
                "robot_silent_minutes",
                AlertKind.ROBOT_SILENT in chosen,
                "Say after how long a robot is silent.",
            ),
            (
                "gas_low_below_ether",
                AlertKind.GAS_LOW in chosen,
                "Say below which balance to tell you.",
            ),
        ]
        for field, wanted, message in needed:
            if wanted and cleaned.get(field) in (None, "") and field not in self.errors:
                self.add_error(field, message)
        return cleaned

    @property
    def gas_low_below_wei(self) -> int | None:
        ether = self.cleaned_data.get("gas_low_below_ether")
        return None if ether is None else int(ether * WEI_PER_ETHER)


class WebhookEndpointForm(forms.Form):
    url = forms.URLField(
        max_length=500,
        assume_scheme="https",
        label="Webhook URL",
        help_text="Alerts are POSTed here as signed JSON (see the documentation's alerts page).",
    )
