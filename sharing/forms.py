"""Forms of the sharing pages: record filters and grants."""

from django import forms
from django.core.exceptions import ValidationError
from django.db.models import QuerySet

from sharing.models import Record


class DateTimeLocalInput(forms.DateTimeInput):
    input_type = "datetime-local"

    def __init__(self) -> None:
        super().__init__(format="%Y-%m-%dT%H:%M")


class RecordFilterForm(forms.Form):
    """Filters of a record list (GET); times are UTC."""

    topic = forms.ChoiceField(required=False)
    data_type = forms.ChoiceField(label="Type", required=False)
    status = forms.ChoiceField(
        required=False,
        choices=[("", "any"), *Record.Status.choices, ("tampered", "tampered")],
    )
    since = forms.DateTimeField(
        label="From (UTC)",
        required=False,
        widget=DateTimeLocalInput(),
        input_formats=["%Y-%m-%dT%H:%M", "%Y-%m-%dT%H:%M:%S", "%Y-%m-%d"],
    )
    until = forms.DateTimeField(
        label="Until (UTC)",
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

    def filter(self, records: QuerySet[Record]) -> QuerySet[Record]:
        """The records that match; all of them while the filters are invalid."""
        if not self.is_valid():
            return records
        data = self.cleaned_data
        if data.get("topic"):
            records = records.filter(topic=data["topic"])
        if data.get("data_type"):
            records = records.filter(data_type=data["data_type"])
        if data.get("status") == "tampered":
            records = records.filter(tampered_at__isnull=False)
        elif data.get("status"):
            records = records.filter(status=data["status"])
        if data.get("since"):
            records = records.filter(captured_at__gte=data["since"])
        if data.get("until"):
            records = records.filter(captured_at__lte=data["until"])
        if data.get("owner"):
            records = records.filter(owner__user__username=data["owner"])
        return records


class GrantForm(forms.Form):
    grantee = forms.CharField(
        label="Username or EOA address",
        max_length=150,
        help_text="The owner who may read all your records, e.g. bob or 0x3f5c…",
        widget=forms.TextInput(attrs={"autocomplete": "off", "spellcheck": "false"}),
    )


class GrantRevokeForm(forms.Form):
    grantee = forms.CharField(max_length=150, widget=forms.HiddenInput)
