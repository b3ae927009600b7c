"""Forms of the sharing pages: record filters and grants."""

from typing import Any

from django import forms
from django.core.exceptions import ValidationError
from django.db.models import QuerySet

from sharing.models import Record
from sharing.selectors import RECORD_FILTER_STATUSES


class DateTimeLocalInput(forms.DateTimeInput):
    input_type = "datetime-local"

    def __init__(self) -> None:
        super().__init__(format="%Y-%m-%dT%H:%M")


class RecordFilterForm(forms.Form):
    """Filters of a record list (GET); times are UTC, the range half-open: from `since`,
    before `until` (as in the API). `filters()` gives them to `record_list_filtered`."""

    topic = forms.ChoiceField(required=False)
    data_type = forms.ChoiceField(label="Type", required=False)
    status = forms.ChoiceField(required=False, choices=[("", "any"), *RECORD_FILTER_STATUSES])
    since = forms.DateTimeField(
        label="From (UTC)",
        required=False,
        widget=DateTimeLocalInput(),
        input_formats=["%Y-%m-%dT%H:%M", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d"],
    )
    until = forms.DateTimeField(
        label="Before (UTC)",
        required=False,
        widget=DateTimeLocalInput(),
        input_formats=["%Y-%m-%dT%H:%M", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d"],
    )
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

    def clean(self) -> dict:
        cleaned = super().clean()
        since, until = cleaned.get("since"), cleaned.get("until")
        if since and until and since > until:
            raise ValidationError("The start of the time range is after its end.")
        return cleaned

    def filters(self) -> dict[str, Any]:
        """The filters given, as `record_list_filtered` takes them; none while invalid."""
        if not self.is_bound or not self.is_valid():
            return {}
        return {name: value for name, value in self.cleaned_data.items() if value}


class GrantForm(forms.Form):
    grantee = forms.CharField(
        label="Username or EOA address",
        max_length=150,
        help_text="The owner who may read all your records, e.g. bob or 0x3f5c…",
        widget=forms.TextInput(attrs={"autocomplete": "off", "spellcheck": "false"}),
    )


class GrantRevokeForm(forms.Form):
    grantee = forms.CharField(max_length=150, widget=forms.HiddenInput)
