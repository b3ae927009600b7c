"""What the API views of sharing share: serializer fields, the record selection's input
(one serializer for every request that selects records), the pagination, the robot-only
permission, the schema's security requirements and refusal wording, and the small helpers
of the caller (its credential, a record id that refuses like a record not seen)."""

import base64
import binascii
import dataclasses
import uuid
from typing import Any, ClassVar

from django.core.validators import ProhibitNullCharactersValidator, RegexValidator
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, extend_schema_field
from rest_framework import serializers
from rest_framework.pagination import LimitOffsetPagination
from rest_framework.permissions import BasePermission
from rest_framework.request import Request
from rest_framework.utils.urls import remove_query_param, replace_query_param
from rest_framework.views import APIView

from accounts.authentication import caller_owner_token, caller_robot
from accounts.models import OwnerToken
from sharing.errors import NOT_VISIBLE, RecordNotFound
from sharing.models import Credential, Record
from sharing.selection import (
    MAX_SELECTED_ROBOTS,
    MAX_SELECTED_TOPICS,
    MAX_TOPIC_LENGTH,
    RecordSelection,
)
from sharing.selectors.record_pages import CURSOR_PATTERN, BadCursor, RecordCursor

# A username is at most 150 characters, an address 42.
MAX_OWNER_IDENTIFIER = 150
NO_NUL = "NUL characters are not allowed"

ROBOT_ONLY = [{"robotToken": []}]
# Content and grants: the owner, signed in or with an owner API token; never a robot token.
OWNER_ONLY = [{"ownerToken": []}, {"cookieAuth": []}]
READ, SHARE, DELETE = OwnerToken.Scope.READ, OwnerToken.Scope.SHARE, OwnerToken.Scope.DELETE
ROBOT_REFUSED = (
    "`permission_denied`: a robot token (it only uploads and reads its own uploads); "
    "`insufficient_scope`: an owner API token without the `{scope}` scope"
)
# The 429 of an operation that has records integrity-checked (sharing/verification/budget.py).
CHECKS_OVER_BUDGET = (
    "`rate_limited`: wait for `Retry-After` seconds; `check_budget_exceeded`: the records this "
    "asks to check are more than the caller's budget of checks (`CHECK_BUDGET`) holds now: "
    "nothing was checked or charged, ask again after `Retry-After` seconds (or for fewer)"
)
# The names of a record selection's values, in every request that selects records.
SELECTION_FIELDS = tuple(field.name for field in dataclasses.fields(RecordSelection))
RECORD_ID = OpenApiParameter(
    "record_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the record's id"
)


@extend_schema_field(
    {
        "type": "string",
        "format": "byte",
        "minLength": 1,
        "pattern": r"^(?:[A-Za-z0-9+/]{4})*(?:[A-Za-z0-9+/]{2}==|[A-Za-z0-9+/]{3}=)?$",
    }
)
class Base64EnvelopeField(serializers.Field):
    """An envelope v1 as standard base64 (RFC 4648, with padding)."""

    default_error_messages = {
        "not_text": "an envelope is sent as a base64 string",
        "blank": "an envelope cannot be empty",
        "not_base64": "not valid base64",
    }

    def to_internal_value(self, data: Any) -> bytes:
        if not isinstance(data, str):
            self.fail("not_text")
        if not data:
            self.fail("blank")
        try:
            return base64.b64decode(data, validate=True)
        except (binascii.Error, ValueError):
            self.fail("not_base64")

    def to_representation(self, value: bytes) -> str:
        return base64.b64encode(value).decode("ascii")


class TextField(serializers.CharField):
    """A string and only a string (DRF's CharField takes 5 for "5"), without NUL characters,
    which the schema says too (a database may refuse them)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.validators = [
            validator
            for validator in self.validators
            if not isinstance(validator, ProhibitNullCharactersValidator)
        ]
        self.validators.append(RegexValidator(r"^[^\x00]*$", message=NO_NUL))

    def to_internal_value(self, data: Any) -> str:
        if not isinstance(data, str):
            self.fail("invalid")
        return super().to_internal_value(data)


class NullIfBlankCharField(serializers.CharField):
    """A text attribute that is blank until something happens, shown as null until then."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(allow_null=True, read_only=True, **kwargs)

    def to_representation(self, value: Any) -> str | None:
        return str(value) if value else None


class MomentField(serializers.DateTimeField):
    """An ISO 8601 moment of a window. Left out, the window has no such bound; sent blank in a
    query (`until=`), it is refused as the wrong format, not taken as left out (DRF's form
    reading), so that what the schema says is invalid is answered 400."""

    def get_value(self, dictionary: Any) -> Any:
        value = super().get_value(dictionary)
        if value is serializers.empty and dictionary.get(self.field_name) == "":
            return ""
        return value


class RecordSelectionSerializer(serializers.Serializer):
    """The input of a record selection (sharing.selection.RecordSelection): robots and topics
    (absent or empty: all) and a capture-time window [since, until), within the bounds that
    `RecordSelection.of` holds. `selection()` gives the four values by RecordSelection's names,
    as the services take them (they make the RecordSelection and refuse what it refuses).

    The one definition of these fields for every request that selects records (a grant's terms,
    an export, an export's count); each says its own words (`selection_help`, by field) and
    whether `since` and `until` may be sent as null (`window_nullable`)."""

    selection_help: ClassVar[dict[str, str]] = {}
    window_nullable: ClassVar[bool] = False

    robots = serializers.ListField(
        child=serializers.UUIDField(), required=False, max_length=MAX_SELECTED_ROBOTS
    )
    topics = serializers.ListField(
        child=TextField(max_length=MAX_TOPIC_LENGTH),
        required=False,
        max_length=MAX_SELECTED_TOPICS,
    )
    since = MomentField(required=False)
    until = MomentField(required=False)

    def get_fields(self) -> dict[str, serializers.Field]:
        fields = super().get_fields()
        for name in SELECTION_FIELDS:
            fields[name].help_text = self.selection_help.get(name)
        for name in ("since", "until"):
            fields[name].allow_null = self.window_nullable
        return fields

    def selection(self) -> dict[str, Any]:
        """robots, topics, since and until as given (absent: all robots, all topics, no bound)."""
        data = self.validated_data
        return {
            "robots": data.get("robots", ()),
            "topics": data.get("topics", ()),
            "since": data.get("since"),
            "until": data.get("until"),
        }


class RecordPagination(LimitOffsetPagination):
    """`?limit=&offset=`, refusing values out of range instead of guessing."""

    default_limit = 50
    max_limit = 500
    max_offset = 10**9

    def get_limit(self, request: Request) -> int:
        return self._bounded(request, self.limit_query_param, 1, self.max_limit, self.default_limit)

    def get_offset(self, request: Request) -> int:
        return self._bounded(request, self.offset_query_param, 0, self.max_offset, 0)

    @staticmethod
    def _bounded(request: Request, name: str, lowest: int, highest: int, default: int) -> int:
        raw = request.query_params.get(name)
        if raw is None:
            return default
        if not (raw.isascii() and raw.isdigit() and len(raw) <= 10):
            raise serializers.ValidationError({name: [f"must be an integer {lowest}..{highest}"]})
        value = int(raw)
        if not lowest <= value <= highest:
            raise serializers.ValidationError({name: [f"must be an integer {lowest}..{highest}"]})
        return value

    def get_schema_operation_parameters(self, view: APIView) -> list[dict[str, Any]]:
        return [
            {
                "name": self.limit_query_param,
                "required": False,
                "in": "query",
                "description": "records per page",
                "schema": {"type": "integer", "minimum": 1, "maximum": self.max_limit},
            },
            {
                "name": self.offset_query_param,
                "required": False,
                "in": "query",
                "description": "records to skip",
                "schema": {"type": "integer", "minimum": 0, "maximum": self.max_offset},
            },
        ]


class RecordKeysetPagination(RecordPagination):
    """The record list by capture time, newest first: `?after=<cursor>` (the `next` link) is
    the page after a record, so a page stays what it was while robots upload (issue 48); a
    cursor is (captured_at, id), `2026-03-01T12:00:00.000000Z_<uuid hex>`. `?offset=` still
    pages by offset, for the clients written before."""

    cursor_query_param = "after"

    def paginate_queryset(
        self, queryset: Any, request: Request, view: APIView | None = None
    ) -> list[Record] | None:
        after = None
        if (raw := request.query_params.get(self.cursor_query_param)) is not None:  # "" too
            try:
                after = RecordCursor.parse(raw)
            except BadCursor:  # refused whatever else is asked, an offset too
                message = "must be the cursor of a `next` link"
                raise serializers.ValidationError({self.cursor_query_param: [message]}) from None
        if self.offset_query_param in request.query_params:
            self.after_records = None
            return super().paginate_queryset(queryset, request, view)
        self.request = request
        self.limit = self.get_limit(request)
        self.count = self.get_count(queryset)
        records = queryset.order_by("-captured_at", "-id")
        if after is not None:
            records = records.filter(after.q_before())
        page = list(records[: self.limit + 1])
        self.after_records = page[self.limit - 1] if len(page) > self.limit else False
        return page[: self.limit]

    def get_next_link(self) -> str | None:
        if self.after_records is None:
            return super().get_next_link()
        if not self.after_records:
            return None
        url = remove_query_param(self.request.build_absolute_uri(), self.offset_query_param)
        cursor = str(RecordCursor.of(self.after_records))
        return replace_query_param(url, self.cursor_query_param, cursor)

    def get_previous_link(self) -> str | None:
        return super().get_previous_link() if self.after_records is None else None

    def get_schema_operation_parameters(self, view: APIView) -> list[dict[str, Any]]:
        return [
            *super().get_schema_operation_parameters(view),
            {
                "name": self.cursor_query_param,
                "required": False,
                "in": "query",
                "description": "the records captured before this cursor (the `next` link's)",
                "schema": {"type": "string", "pattern": CURSOR_PATTERN},
            },
        ]


class IsRobot(BasePermission):
    message = "uploads need a robot token: `Authorization: Token <key>`"

    def has_permission(self, request: Request, view: APIView) -> bool:
        return caller_robot(request) is not None


def record_uuid(record_id: str) -> uuid.UUID:
    try:
        return uuid.UUID(record_id)
    except ValueError:
        raise RecordNotFound(NOT_VISIBLE) from None


def refuse_unseen(request: Request, record_id: uuid.UUID) -> None:
    """A record the caller may not see: 404 whether it exists or not, outside a grant's scope
    or not (nothing tells it exists)."""
    raise RecordNotFound(NOT_VISIBLE)


def caller_credential(request: Request) -> tuple[str, OwnerToken | None]:
    """The owner's credential behind a request, as the access log records it: an owner API
    token (with the token), else the browser session."""
    token = caller_owner_token(request)
    return (Credential.SESSION if token is None else Credential.TOKEN), token
