"""Forms of the sharing pages: record and audit filters, and grants."""

from typing import Any

from django import forms
from django.core.exceptions import ValidationError
from django.db.models import QuerySet

from accounts.models import ChainActivity, Owner, Robot
from sharing.models import Record
from sharing.selectors import RECORD_FILTER_STATUSES


class DateTimeLocalInput(forms.DateTimeInput):
    input_type = "datetime-local"

    def __init__(self) -> None:
        super().__init__(format="%Y-%m-%dT%H:%M")


def _period_field(label: str) -> forms.DateTimeField:
    return forms.DateTimeField(
        label=label,
        required=False,
        widget=DateTimeLocalInput(),
        input_formats=["%Y-%m-%dT%H:%M", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d"],
    )


class PeriodFilterForm(forms.Form):
    """A GET filter with a period: times are UTC, the range half-open, from `since`, before
    `until` (as in the API). `filters()` gives the values given to the page's selector."""

    since = _period_field("From (UTC)")
    until = _period_field("Before (UTC)")

    def clean(self) -> dict:
        cleaned = super().clean()
        since, until = cleaned.get("since"), cleaned.get("until")
        if since and until and since > until:
            raise ValidationError("The start of the time range is after its end.")
        return cleaned

    def filters(self) -> dict[str, Any]:
        """The filters given, as the page's selector takes them; none while invalid."""
        if not self.is_bound or not self.is_valid():
            return {}
        return {name: value for name, value in self.cleaned_data.items() if value}


class RecordFilterForm(PeriodFilterForm):
    """Filters of a record list (GET), for `record_list_filtered`."""

    topic = forms.ChoiceField(required=False)
    data_type = forms.ChoiceField(label="Type", required=False)
    status = forms.ChoiceField(required=False, choices=[("", "any"), *RECORD_FILTER_STATUSES])
    owner = forms.ChoiceField(required=False)

    def __init__(self, data: object, *, records: QuerySet[Record], with_owner: bool) -> None:
        super().__init__(data)
        topics = records.order_by("topic").values_list("topic", flat=True).distinct()
        types = records.order_by("data_type").values_list("data_type", flat=True).distinct()
        self.fields["topic"].choices = [("", "any"), *((t, t) for t in topics)]
        self.fields["data_type"].choices = [("", "any"), *((t, t) for t in types)]
        if with_owner:
            owners = (
                records.order_by("owner__user__username")
                .values_list("owner__user__username", flat=True)
                .distinct()
            )
            self.fields["owner"].choices = [("", "any"), *((o, o) for o in owners)]
        else:
            del self.fields["owner"]


class AuditFilterForm(PeriodFilterForm):
    """Filters of the audit page (GET), for `audit_page_of_owner`: the kind of transaction,
    the anchoring of one of the owner's robots, and the period the worker saw it in."""

    kind = forms.ChoiceField(required=False, choices=[("", "any"), *ChainActivity.Kind.choices])
    robot = forms.ChoiceField(label="Anchoring of robot", required=False)

    def __init__(self, data: object, *, owner: Owner) -> None:
        super().__init__(data)
        robots = Robot.objects.filter(owner=owner).order_by("name").values_list("id", "name")
        self.fields["robot"].choices = [("", "any"), *((str(pk), name) for pk, name in robots)]


class GrantForm(forms.Form):
    grantee = forms.CharField(
        label="Username or EOA address",
        max_length=150,
        help_text="The owner who may read all your records, e.g. bob or 0x3f5c…",
        widget=forms.TextInput(attrs={"autocomplete": "off", "spellcheck": "false"}),
    )


class GrantRevokeForm(forms.Form):
    grantee = forms.CharField(max_length=150, widget=forms.HiddenInput)
