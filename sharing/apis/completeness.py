"""`/api/v1/records/completeness/`: per stream (signer, topic) of a window the caller may see,
the first and last topic_seq, the count, and every gap with the portal's reason
(sharing/selectors/completeness.py). The schema of `streams` is shared with the series."""

from typing import Any

from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from core.api_errors import error_responses
from sharing.apis.fields import OWNER_ONLY, READ, ROBOT_REFUSED, MomentField, TextField
from sharing.selection import MAX_TOPIC_LENGTH
from sharing.selectors.completeness import GAP_REASONS, completeness_visible_to
from sharing.services.completeness import records_missing_alerts_raise

GAP_SCHEMA = {
    "type": "object",
    "required": ["from", "to", "reason"],
    "properties": {
        "from": {"type": "integer", "description": "the first topic_seq of the gap"},
        "to": {"type": "integer", "description": "the last topic_seq of the gap (in it)"},
        "reason": {
            "type": "string",
            "enum": list(GAP_REASONS),
            "description": "`deleted` (by the owner, or with the owner's account), "
            "`retention` (the robot's retention policy), or `missing`: the portal holds "
            "nothing for these numbers and no deletion explains it",
        },
        "at": {
            "type": "string",
            "format": "date-time",
            "description": "when they were deleted (the latest of the gap); only for "
            "`deleted` and `retention`",
        },
    },
}
STREAM_SCHEMA = {
    "type": "object",
    "required": ["signer", "topic", "robot", "first", "last", "count", "gaps"],
    "properties": {
        "signer": {
            "type": "string",
            "description": "the robot key that counts the stream (SM3 of its SM2 public key)",
        },
        "topic": {"type": "string"},
        "robot": {"type": "string", "format": "uuid", "description": "the robot's id"},
        "first": {"type": "integer", "description": "the lowest topic_seq in the window"},
        "last": {"type": "integer", "description": "the highest topic_seq in the window"},
        "count": {"type": "integer", "description": "records of the stream in the window"},
        "gaps": {"type": "array", "items": GAP_SCHEMA, "description": "in topic_seq order"},
    },
}
STREAMS_SCHEMA = {
    "type": "array",
    "items": STREAM_SCHEMA,
    "description": "per signer and topic (provenance v2 records), the first and last "
    "topic_seq of the window, the count, and every number between them no record holds: "
    "`last - first + 1 = count + sum of the gaps' sizes`",
}
UNCOUNTED_SCHEMA = {
    "type": "integer",
    "description": "records in the window that no signer counts (provenance v1 or unsigned: "
    "no topic_seq)",
}


class RecordCompletenessApi(APIView):
    """`GET /api/v1/records/completeness/`: is anything missing in a window the caller may
    see, and why."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read records' completeness")]

    class InputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "CompletenessQuery"

        robot = serializers.UUIDField(required=False, help_text="robot id")
        topic = TextField(required=False, max_length=MAX_TOPIC_LENGTH, help_text="e.g. /odom")
        since = MomentField(required=False, help_text="captured at or after (ISO 8601)")
        until = MomentField(
            required=False, help_text="captured before, not at (ISO 8601): [since, until)"
        )

        def validate(self, data: dict[str, Any]) -> dict[str, Any]:
            since, until = data.get("since"), data.get("until")
            if since and until and since >= until:
                raise serializers.ValidationError("`since` must be before `until`")
            return data

    ANSWER = {
        "type": "object",
        "required": ["streams", "uncounted"],
        "properties": {"streams": STREAMS_SCHEMA, "uncounted": UNCOUNTED_SCHEMA},
    }

    @extend_schema(
        operation_id="records_completeness",
        summary="Is anything missing: each stream's first, last, count and gaps in a window",
        description=(
            "Of the records captured in [since, until) that the caller may see (its own, or "
            "within a live grant's scope; deleted records included, as the reason for a gap), "
            "of one robot and topic if given: per stream (signer, topic) the first and last "
            "topic_seq, the count, and each gap with its reason. The portal's reading of its "
            "rows, checked by anyone holding the window's records (`authros-verify "
            "--complete`). Numbers before the first or after the last record of the window "
            "are not in it. A robot or topic outside the caller's scope answers as one that "
            "does not exist: no stream. A `missing` gap alerts the robot's owner (alert "
            "`records_missing`, once per gap). A session or an owner API token with the "
            "`read` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[InputSerializer],
        responses={
            200: OpenApiResponse(ANSWER, description="the streams of the window"),
            **error_responses(
                400,
                401,
                403,
                e400="`invalid_request`: a parameter malformed, or `since` not before `until`",
                e403=ROBOT_REFUSED.format(scope="read"),
            ),
        },
    )
    def get(self, request: Request) -> Response:
        given = self.InputSerializer(data=request.query_params.dict())
        given.is_valid(raise_exception=True)
        completeness = completeness_visible_to(caller_owner(request), **given.validated_data)
        # A gap no deletion explains is told to the robot's owner, once per gap.
        records_missing_alerts_raise(completeness)
        return Response(completeness.as_json())
