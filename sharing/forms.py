"""Forms of the sharing pages: record, audit and access-log filters, the record selection's
input (one mixin for a grant's terms, an export and a deletion), grants, the account's
deletion."""

from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any, ClassVar

from django import forms
from django.core.exceptions import ValidationError
from django.db.models import QuerySet

from accounts.models import ChainActivity, Owner, Robot
from sharing.models import Credential, Record, Verdict
from sharing.selection import MAX_TOPIC_LENGTH
from sharing.selectors.access import ACCESS_LOG_DIRECTIONS, ACCESS_LOG_INCOMING, ACCESS_LOG_OUTGOING
from sharing.selectors.records import RECORD_FILTER_STATUSES, RECORD_SORT_DEFAULT, RECORD_SORTS


class UtcDateTimeInput(forms.DateTimeInput):
    """A UTC time typed as text, "2026-05-01 14:30": 24-hour, whatever the browser's locale
    (a datetime-local input shows "02:30 PM" in an en-US browser, beside a "(UTC)" label)."""

    input_type = "text"

    def __init__(self) -> None:
        super().__init__(
            format="%Y-%m-%d %H:%M",
            attrs={
                "placeholder": "YYYY-MM-DD HH:MM",
                "autocomplete": "off",
                "spellcheck": "false",
                "size": "16",
            },
        )


class _PeriodField(forms.DateTimeField):
    """A time a page filters by: one whose UTC falls outside the years 1-9999 (year 1 at +14:00,
    year 9999 at -14:00) is a form error, not an overflow in the query."""

    def to_python(self, value: Any) -> datetime | None:
        moment = super().to_python(value)
        if moment is not None and moment.tzinfo is not None:
            try:
                moment.astimezone(UTC)
            except OverflowError:
                raise ValidationError(
                    "Enter a time between the years 1 and 9999 in UTC.", code="invalid"
                ) from None
        return moment


def _period_field(label: str) -> forms.DateTimeField:
    return _PeriodField(
        label=label,
        required=False,
        widget=UtcDateTimeInput(),
        input_formats=[
            "%Y-%m-%d %H:%M",
            "%Y-%m-%d %H:%M:%S",
            "%Y-%m-%dT%H:%M",
            "%Y-%m-%dT%H:%M:%S",
            "%Y-%m-%d",
        ],
    )


class PeriodFilterForm(forms.Form):
    """A GET filter with a period: times are UTC, the range half-open, from `since`, before
    `until` (as in the API). `filters()` gives the values given to the page's selector.

    A filter that does not hold (a date the API refuses, a robot that is not the reader's, an
    unknown sort key, an end before the start) is an error of its own field, and left out of
    `filters()`: a list page shows what the other filters select, with `left_out()` saying
    what was dropped and why."""

    since = _period_field("From (UTC)")
    until = _period_field("Before (UTC)")

    def clean(self) -> dict:
        cleaned = super().clean()
        since, until = cleaned.get("since"), cleaned.get("until")
        if since and until and since > until:
            self.add_error("until", "The start of the time range is after its end.")
        return cleaned

    def filters(self) -> dict[str, Any]:
        """The filters given that hold, as the page's selector takes them."""
        if not self.is_bound:
            return {}
        self.is_valid()
        return {name: value for name, value in self.cleaned_data.items() if value}

    def left_out(self) -> str:
        """What `filters()` dropped and why, for the page to say; empty when nothing was."""
        if not self.is_bound or self.is_valid():
            return ""
        said = []
        for name, errors in self.errors.items():
            field = self.fields.get(name)
            label = field.label or name.replace("_", " ").capitalize() if field else ""
            said.append(f"{label}: {' '.join(errors)}" if label else " ".join(errors))
        return "Left out of the filters, as they do not hold: " + "; ".join(said)


class RecordSelectionForm(forms.Form):
    """Form mixin: a page's input of a record selection (sharing.selection.RecordSelection), the
    one definition of its fields for every form that selects records (a grant's terms, an
    export, a deletion).

    Robots and topics are either several, ticked (none: all; RecordSelection.of: a grant, an
    export) or, with `one_of_each`, one of each chosen from a list with "any" (as the record
    lists filter; RecordSelection.from_filters: a deletion); the capture-time window is
    [since, until), UTC. Each form says its own words (`selection_labels`, `selection_help`),
    is offered its robots and topics by `offer`, and checks the window as it words it. The
    values go to the service by `selection()`, which makes the RecordSelection and refuses
    what it refuses.
    """

    one_of_each: ClassVar[bool] = False
    selection_labels: ClassVar[dict[str, str]] = {}
    selection_help: ClassVar[dict[str, str]] = {}

    since = _period_field("From (UTC)")
    until = _period_field("Before (UTC)")

    def offer(self, *, robots: Iterable[tuple[str, str]], topics: Iterable[str]) -> None:
        """The robots (id, label) and topics to choose from, as the selection's fields."""
        robot_choices = [(str(pk), label) for pk, label in robots]
        topic_choices = [(topic, topic) for topic in topics]
        if self.one_of_each:
            shown = {
                "robot": forms.ChoiceField(required=False, choices=[("", "any"), *robot_choices]),
                "topic": forms.ChoiceField(required=False, choices=[("", "any"), *topic_choices]),
            }
        else:
            shown = {
                name: forms.MultipleChoiceField(
                    required=False,
                    widget=forms.CheckboxSelectMultiple,
                    choices=choices,
                    label=self.selection_labels.get(name),
                    help_text=self.selection_help.get(name, ""),
                )
                for name, choices in (("robots", robot_choices), ("topics", topic_choices))
            }
        self.fields.update(shown)
        for name in ("since", "until"):
            if name in self.selection_labels:
                self.fields[name].label = self.selection_labels[name]
        self.order_fields(self.field_order)

    def selection(self) -> dict[str, Any]:
        """The values given, by the names the services take: robots, topics, since, until
        (robot, topic, since, until with `one_of_each`); empty or None where none is given."""
        names = ("robot", "topic") if self.one_of_each else ("robots", "topics")
        return {name: self.cleaned_data.get(name) for name in (*names, "since", "until")}


def _sort_choices() -> list[tuple[str, str]]:
    names = {"captured": "capture time", "robot": "robot", "topic": "topic", "status": "status"}
    choices = []
    for key in RECORD_SORTS:
        newest = key == "captured"
        choices.append((f"-{key}", f"{names[key]}, {'newest' if newest else 'Z to A'} first"))
        choices.append((key, f"{names[key]}, {'oldest' if newest else 'A to Z'} first"))
    return choices


class RecordFilterForm(PeriodFilterForm):
    """Filters and sort order of a record list (GET), for `record_list_filtered` and
    `record_list_sorted`; `sort` is one of RECORD_SORTS (a form error otherwise)."""

    robot = forms.ChoiceField(required=False)
    topic = forms.ChoiceField(required=False)
    data_type = forms.ChoiceField(label="Type", required=False)
    status = forms.ChoiceField(required=False, choices=[("", "any"), *RECORD_FILTER_STATUSES])
    owner = forms.ChoiceField(required=False)
    sort = forms.ChoiceField(label="Sort by", required=False, choices=_sort_choices())

    def __init__(
        self,
        data: object,
        *,
        records: QuerySet[Record],
        robots: QuerySet[Robot],
        with_owner: bool,
    ) -> None:
        super().__init__(data)
        self.fields["robot"].choices = [
            ("", "any"),
            *(
                (
                    str(robot.pk),
                    f"{robot.name} ({robot.owner.username})" if with_owner else robot.name,
                )
                for robot in robots
            ),
        ]
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

    def filters(self) -> dict[str, Any]:
        return {name: value for name, value in super().filters().items() if name != "sort"}

    def sort_order(self) -> str:
        """The sort order asked for; the default when it is none or not one of RECORD_SORTS."""
        if not self.is_bound:
            return RECORD_SORT_DEFAULT
        self.is_valid()
        return self.cleaned_data.get("sort") or RECORD_SORT_DEFAULT


class TopicRangeForm(PeriodFilterForm):
    """The capture-time range of a topic's plot or image gallery (GET); both ends needed."""

    def clean(self) -> dict:
        cleaned = super().clean()
        for name in ("since", "until"):
            if name in cleaned and cleaned[name] is None:
                self.add_error(name, "Give both ends of the time range.")
        return cleaned


class AuditFilterForm(PeriodFilterForm):
    """Filters of the audit page (GET), for `audit_page_of_owner`: the kind of transaction,
    the anchoring of one of the owner's robots, and the period the worker saw it in."""

    kind = forms.ChoiceField(required=False, choices=[("", "any"), *ChainActivity.Kind.choices])
    robot = forms.ChoiceField(label="Anchoring of robot", required=False)

    def __init__(self, data: object, *, owner: Owner) -> None:
        super().__init__(data)
        robots = Robot.objects.filter(owner=owner).order_by("name").values_list("id", "name")
        self.fields["robot"].choices = [("", "any"), *((str(pk), name) for pk, name in robots)]


class GrantForm(RecordSelectionForm):
    """Give access (or, with `change`, change a grant's terms): who, and which records until
    when. Nothing ticked and no dates: all records, without expiry."""

    selection_labels: ClassVar[dict[str, str]] = {
        "robots": "Robots",
        "topics": "Topics",
        "since": "Captured from (UTC)",
        "until": "Captured before (UTC)",
    }
    selection_help: ClassVar[dict[str, str]] = {
        "robots": "None ticked: all your robots, also those you add later.",
        "topics": "None ticked: all topics.",
    }
    field_order = (
        "grantee",
        "robots",
        "topics",
        "since",
        "until",
        "expires_at",
        "change",
        "confirm_all",
    )

    grantee = forms.CharField(
        label="Username or EOA address",
        max_length=150,
        help_text="The owner who may read your records, e.g. bob or 0x3f5c…",
        widget=forms.TextInput(attrs={"autocomplete": "off", "spellcheck": "false"}),
        error_messages={"required": "Enter the username or address of the owner to share with."},
    )
    expires_at = _period_field("Access ends (UTC)")
    change = forms.BooleanField(required=False, widget=forms.HiddenInput)
    # Set by the confirmation page: the owner read that the grant covers every record, for ever.
    confirm_all = forms.BooleanField(required=False, widget=forms.HiddenInput)

    def __init__(
        self, data: object = None, *, robots: list[Robot], topics: list[str], **kwargs: Any
    ) -> None:
        super().__init__(data, **kwargs)
        self.offer(robots=((robot.pk, robot.name) for robot in robots), topics=topics)
        self.fields[
            "expires_at"
        ].help_text = "Leave empty for access until you revoke it. At least 5 minutes from now."
        for name in ("since", "until", "expires_at"):
            self.fields[name].error_messages["invalid"] = (
                "Enter a date and time, e.g. 2026-05-01 14:30 (24-hour, UTC)."
            )

    def clean(self) -> dict:
        cleaned = super().clean()
        since, until = cleaned.get("since"), cleaned.get("until")
        if since and until and since >= until:
            self.add_error("until", "“Captured before” must be later than “Captured from”.")
        return cleaned

    @property
    def needs_confirmation(self) -> bool:
        """Nothing chosen (every record of every robot, any time, no expiry) and not confirmed
        yet: the grant waits for the owner to confirm that on a page of its own."""
        data = self.cleaned_data
        chosen = ("robots", "topics", "since", "until", "expires_at")
        return not data.get("confirm_all") and not any(data.get(name) for name in chosen)


class GrantRevokeForm(forms.Form):
    grantee = forms.CharField(max_length=150, widget=forms.HiddenInput)


class AccessLogFilterForm(PeriodFilterForm):
    """Filters of the access log (GET), for `access_list_filtered`: which side of the log,
    who viewed (or whose record), robot, topic, verdict, credential and the time of the view.

    `choices` is sharing.selectors.access.access_log_filter_choices for the side asked for.
    """

    since = _period_field("Viewed from (UTC)")
    until = _period_field("Viewed before (UTC)")
    # Chosen by the page's tabs; kept in the form so that filtering stays on the same side.
    direction = forms.ChoiceField(
        required=False, choices=ACCESS_LOG_DIRECTIONS, widget=forms.HiddenInput
    )
    viewer = forms.CharField(label="Viewer", required=False, max_length=150)
    owner = forms.CharField(label="Owner", required=False, max_length=150)
    robot = forms.ChoiceField(required=False)
    topic = forms.CharField(required=False, max_length=MAX_TOPIC_LENGTH)
    verdict = forms.ChoiceField(required=False, choices=[("", "any"), *Verdict.Outcome.choices])
    credential = forms.ChoiceField(
        required=False,
        choices=[("", "any"), *((v, label) for v, label in Credential.choices if v)],
    )
    # The owner's own reads of their own records are not listed unless asked for (issue 48).
    mine = forms.BooleanField(label="Include my own views", required=False)

    def __init__(self, data: object, *, choices: dict[str, QuerySet]) -> None:
        super().__init__(data)
        self.fields["robot"].choices = [
            ("", "any"),
            *((str(pk), f"{name} ({owner})") for pk, name, owner in choices["robots"]),
        ]
        self.topics = choices["topics"]
        self.people = choices["people"]
        for name in ("viewer", "owner", "topic"):
            self.fields[name].widget.attrs.update(
                {"list": f"{name}-choices", "autocomplete": "off", "spellcheck": "false"}
            )

    @staticmethod
    def direction_of(data: object) -> str:
        """The side of the log asked for, before validation (to offer its choices): one of
        ACCESS_LOG_DIRECTIONS, incoming unless the other is asked for by name."""
        asked = data.get("direction") if hasattr(data, "get") else None
        return ACCESS_LOG_OUTGOING if asked == ACCESS_LOG_OUTGOING else ACCESS_LOG_INCOMING

    def filters(self) -> dict[str, Any]:
        found = super().filters()
        found.pop("direction", None)
        found.pop("mine", None)
        return found

    def with_own_views(self, owner_name: str) -> bool:
        """Whether the owner's own views are listed: asked for, or the viewer filter names
        the owner."""
        filters = self.filters()
        return bool(self.is_bound and self.is_valid() and self.cleaned_data.get("mine")) or (
            filters.get("viewer") == owner_name
        )


class ExportForm(RecordSelectionForm, PeriodFilterForm):
    """What to export: robots and topics the owner may view (none ticked: all), a period."""

    selection_labels: ClassVar[dict[str, str]] = {
        "robots": "Robots (none ticked: all)",
        "topics": "Topics (none ticked: all)",
    }

    def __init__(self, data: object, *, robots: QuerySet[Robot], topics: list[str]) -> None:
        super().__init__(data)
        self.offer(
            robots=((robot.pk, f"{robot.name} ({robot.owner.username})") for robot in robots),
            topics=topics,
        )


class RecordDeleteSelectionForm(RecordSelectionForm, PeriodFilterForm):
    """Which of the owner's records to delete: a robot, a topic, a capture-time range; at
    least one of them (never "everything" by an empty form)."""

    one_of_each: ClassVar[bool] = True
    field_order = ("robot", "topic", "since", "until")

    def __init__(self, data: object, *, owner: Owner) -> None:
        super().__init__(data)
        robots = Robot.objects.filter(owner=owner).order_by("name").values_list("id", "name")
        topics = (
            Record.objects.live()
            .filter(owner=owner)
            .order_by("topic")
            .values_list("topic", flat=True)
            .distinct()
        )
        self.offer(robots=robots, topics=topics)

    def clean(self) -> dict:
        cleaned = super().clean()
        if not any(cleaned.get(name) for name in ("robot", "topic", "since", "until")):
            raise ValidationError(
                "Choose a robot, a topic or a time range: what to delete.", code="required"
            )
        return cleaned


class AccountDeleteForm(forms.Form):
    """Deleting the account: the owner's password again, and a tick that they read what
    happens."""

    password = forms.CharField(
        label="Your password",
        strip=False,
        widget=forms.PasswordInput(attrs={"autocomplete": "current-password"}),
    )
    understood = forms.BooleanField(
        label="I understand that my records and my account are deleted for good, and that what "
        "is on chain stays there",
    )
