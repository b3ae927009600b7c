"""`/api/v1/access-log/`: who viewed the caller's records, or the caller's own views of
records shared with it."""

from typing import Any

from drf_spectacular.utils import extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from core.api_errors import error_responses
from sharing.access_log import access_log_redacted, access_outcomes
from sharing.apis.fields import (
    MAX_OWNER_IDENTIFIER,
    OWNER_ONLY,
    READ,
    ROBOT_REFUSED,
    MomentField,
    NullIfBlankCharField,
    RecordPagination,
    TextField,
)
from sharing.models import Access, Credential, Verdict
from sharing.selection import MAX_TOPIC_LENGTH
from sharing.selectors.access import (
    ACCESS_LOG_DIRECTIONS,
    ACCESS_LOG_INCOMING,
    access_list_access_log,
    access_list_filtered,
)


class AccessLogTokenSerializer(serializers.Serializer):
    class Meta:
        ref_name = "AccessLogToken"

    name = serializers.CharField()
    prefix = serializers.CharField(source="token_prefix", help_text="its first characters")


class AccessLogApi(APIView):
    """`GET /api/v1/access-log/`: who read the caller's records, or the caller's own reads of
    records shared with it: the access log page's rows (one per access), with its selectors
    and filters."""

    pagination_class = RecordPagination

    class FilterSerializer(serializers.Serializer):
        class Meta:
            ref_name = "AccessLogFilter"

        direction = serializers.ChoiceField(
            choices=ACCESS_LOG_DIRECTIONS,
            required=False,
            default=ACCESS_LOG_INCOMING,
            help_text="`incoming` (default): every view of your records; `outgoing`: your own "
            "views of records other owners shared with you",
        )
        viewer = TextField(
            required=False, max_length=MAX_OWNER_IDENTIFIER, help_text="viewer's username"
        )
        owner = TextField(
            required=False,
            max_length=MAX_OWNER_IDENTIFIER,
            help_text="the record owner's username (useful with `outgoing`)",
        )
        robot = serializers.UUIDField(required=False, help_text="robot id")
        topic = TextField(required=False, max_length=MAX_TOPIC_LENGTH)
        verdict = serializers.ChoiceField(
            choices=Verdict.Outcome.choices, required=False, help_text="the check's outcome"
        )
        credential = serializers.ChoiceField(
            choices=[value for value in Credential.values if value],
            required=False,
            help_text="the credential the view was made with",
        )
        since = MomentField(required=False, help_text="viewed at or after")
        until = MomentField(
            required=False, help_text="viewed before, not at (ISO 8601): [since, until)"
        )

        def validate(self, data: dict[str, Any]) -> dict[str, Any]:
            since, until = data.get("since"), data.get("until")
            if since and until and since > until:
                raise serializers.ValidationError("`since` is after `until`")
            return data

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "AccessLogEntry"

        id = serializers.IntegerField()
        viewed_at = serializers.DateTimeField(source="created_at")
        kind = serializers.ChoiceField(
            choices=Access.Kind.choices,
            help_text="`view` (a record page or content answer), `page`, `plot`, `export`, "
            "`check` (an operator's check in the admin console)",
        )
        records = serializers.IntegerField(source="count", help_text="records it read")
        viewer = serializers.CharField(source="viewer.username")
        record_owner = serializers.CharField(source="record_owner.username")
        record = serializers.UUIDField(
            source="record_id", allow_null=True, help_text="the record, when it read one"
        )
        robot = serializers.UUIDField(
            source="robot_id", allow_null=True, help_text="when all its records share it"
        )
        robot_name = serializers.CharField(source="robot.name", allow_null=True)
        topic = NullIfBlankCharField(help_text="when all its records share it")
        type = serializers.CharField(
            source="record.data_type", allow_null=True, help_text="ROS message type"
        )
        seq = serializers.IntegerField(source="record.seq", allow_null=True)
        captured_at = serializers.DateTimeField(source="record.captured_at", allow_null=True)
        verdict = serializers.CharField(
            source="outcome",
            help_text="what the checks against the chain found: the one outcome of all its "
            "records (`verified`, `tampered`, `not_anchored_yet`, `no_access`, `deleted`, "
            "`signature_refused`), else `mixed`",
        )
        verified = serializers.IntegerField(help_text="its records found verified")
        refused = serializers.IntegerField(help_text="its records refused, whatever the reason")
        credential = NullIfBlankCharField(
            help_text="`session`, `token` or `operator` (an operator's check in the admin "
            "console); null for views from before the portal recorded it"
        )
        token = AccessLogTokenSerializer(
            allow_null=True,
            read_only=True,
            help_text="your own owner API token, for `token`; null for another owner's",
        )
        operator = serializers.CharField(
            source="checked_by.username",
            allow_null=True,
            read_only=True,
            help_text="the operator, for `operator`",
        )
        block_number = serializers.IntegerField(
            allow_null=True, help_text="the latest block its checks were made against"
        )

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read the access log")]

    @extend_schema(
        operation_id="access_log_list",
        summary="Who viewed your records, and your own views of records shared with you",
        description=(
            "Every read of records (a record's view, a page, a plot, an export, an operator's "
            "check) is one line per record owner, its records' integrity verdicts under it; "
            "this lists the lines newest first, as the access log page does, with what the "
            "checks found and the credential the read was made with. A session, or an owner "
            "API token with the `read` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[FilterSerializer],
        responses={
            200: OutputSerializer(many=True),
            **error_responses(400, 401, 403, e403=ROBOT_REFUSED.format(scope="read")),
        },
    )
    def get(self, request: Request) -> Response:
        filters = self.FilterSerializer(data=request.query_params.dict())
        filters.is_valid(raise_exception=True)
        wanted = dict(filters.validated_data)
        direction = wanted.pop("direction")
        reader = caller_owner(request)
        accesses = access_list_access_log(reader, direction=direction)
        paginator = self.pagination_class()
        page = paginator.paginate_queryset(access_list_filtered(accesses, **wanted), request, self)
        shown = access_outcomes(access_log_redacted(page, reader=reader))
        return paginator.get_paginated_response(self.OutputSerializer(shown, many=True).data)


# --- exports ---------------------------------------------------------------------------------
