"""`/api/v1/records/series/`: numeric fields of a robot's topic over a time range, every
record in it integrity-checked (sharing/series.py), thinned for display as its plot draws it
(sharing/thinning.py); a refresh asks only for the records after the newest one it has."""

from datetime import UTC, datetime, timedelta
from decimal import Decimal

from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from core.api_errors import error_responses
from sharing.apis.completeness import STREAMS_SCHEMA, UNCOUNTED_SCHEMA
from sharing.apis.fields import (
    CHECKS_OVER_BUDGET,
    OWNER_ONLY,
    READ,
    ROBOT_REFUSED,
    TextField,
    caller_credential,
)
from sharing.errors import SeriesRefused
from sharing.selection import MAX_TOPIC_LENGTH
from sharing.series import DEFAULT_POINTS, MAX_FIELDS, MAX_POINTS, series_of, series_query_make
from sharing.services.completeness import records_missing_alerts_raise
from sharing.thinning import Method, Shape, series_thinned

EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
MICROSECOND = timedelta(microseconds=1)


class RecordSeriesApi(APIView):
    """`GET /api/v1/records/series/`: numeric fields of a robot's topic over a time range,
    from every record in it, each integrity-checked (sharing/series.py)."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read records' content")]

    class InputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "SeriesQuery"

        robot = serializers.UUIDField(help_text="the robot's id")
        topic = TextField(max_length=MAX_TOPIC_LENGTH, help_text="the topic, e.g. /odom")
        since = serializers.DateTimeField(help_text="captured at or after (ISO 8601)")
        until = serializers.DateTimeField(help_text="captured before (ISO 8601): [since, until)")
        points = serializers.IntegerField(
            required=False,
            default=DEFAULT_POINTS,
            min_value=2,
            max_value=MAX_POINTS,
            help_text="points answered at most (thinned as `shape` says when there are more)",
        )
        shape = serializers.ChoiceField(
            choices=[(shape.value, shape.value) for shape in Shape],
            required=False,
            default=Shape.TIME.value,
            help_text="`time` (each field over time: each time bucket's lowest and highest "
            "value of each field) or `path` (a trajectory, the first two fields as x and y: "
            "thinned along the path by largest-triangle-three-buckets)",
            error_messages={"invalid_choice": "shape is `time` or `path`, not “{input}”"},
        )
        after = serializers.DecimalField(
            required=False,
            max_digits=17,
            decimal_places=6,
            min_value=0,
            help_text="a refresh: only records captured after this moment (Unix seconds, as "
            "the points' t: the newest point the caller holds) are read and checked",
        )

    # `fields` is not a serializer field's name (a Serializer's own attribute): read apart.
    FIELDS = OpenApiParameter(
        "fields",
        OpenApiTypes.STR,
        OpenApiParameter.QUERY,
        required=True,
        allow_blank=False,
        pattern=r"^[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*(,[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*)*$",
        description=f"up to {MAX_FIELDS} dotted paths into the decoded message (`K` of the "
        "record), comma separated, e.g. position.x,position.y",
    )
    ANSWER = {
        "type": "object",
        "properties": {
            "fields": {"type": "array", "items": {"type": "string"}},
            "points": {
                "type": "array",
                "items": {"type": "array", "items": {"type": "number", "nullable": True}},
                "description": "[t, v1, v2...] oldest first; t in Unix seconds (UTC); a value "
                "is null where the record holds no number at that path",
            },
            "source_records": {"type": "integer", "description": "records in range you may see"},
            "verified": {"type": "integer", "description": "of them, verified against the chain"},
            "refused": {
                "type": "integer",
                "description": "of them, refused by the check (tampered, signature not valid, "
                "no access on chain): never plotted",
            },
            "not_anchored_yet": {
                "type": "integer",
                "description": "of them, not verified because not anchored on chain yet (or "
                "their anchoring gave up): not plotted until they are",
            },
            "without_values": {
                "type": "integer",
                "description": "verified records holding none of the fields as a number",
            },
            "shape": {"type": "string", "enum": [shape.value for shape in Shape]},
            "method": {
                "type": "string",
                "enum": [method.value for method in Method],
                "description": "how the points were thinned: `all` (every verified record "
                "holding a value, or on a path both x and y), `largest-triangle-three-buckets` "
                "(shape path) or `min-max-per-time-bucket` (shape time); every point is one "
                "record's",
            },
            "streams": STREAMS_SCHEMA,
            "uncounted": UNCOUNTED_SCHEMA,
        },
    }

    @extend_schema(
        operation_id="records_series",
        summary="Numeric fields of a robot's topic over time, every record checked",
        description=(
            "Every record of the robot's topic captured in [since, until) that the caller may "
            "read (its own, or within a live grant's scope) is checked against the chain like "
            "a content read; the verified ones' fields are answered, at most `points` rows, "
            "each one record's values: with more, thinned as `shape` draws them (`time`: each "
            "time bucket's rows holding each field's lowest and highest value; `path`: along "
            "the x-y path by largest-triangle-three-buckets), the first and last always kept, "
            "`method` saying which. `after` (a refresh) reads and checks only the records of "
            "the range captured after it. `streams` says, as `/api/v1/records/completeness/` "
            "for these records, whether any is missing and why. The whole answer is one line "
            "of the access log (kind `plot`); a refresh adds its records to the caller's line "
            "of the same plot begun in the last 10 minutes. A session or an owner API token "
            "with the `read` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[InputSerializer, FIELDS],
        responses={
            200: OpenApiResponse(ANSWER, description="the series"),
            **error_responses(
                400,
                401,
                403,
                409,
                503,
                e400="`invalid_request` (a parameter missing or malformed, a shape neither "
                "`time` nor `path`), `invalid_series` (too many fields, a path of fewer than "
                "two, `after` not before `until`, a range too long or holding too many "
                "records)",
                e403=ROBOT_REFUSED.format(scope="read"),
                e429=CHECKS_OVER_BUDGET,
                e409="`identity_check_failed`: the owner's key commitment on chain differs "
                "from the key the portal holds",
            ),
        },
    )
    def get(self, request: Request) -> Response:
        given = self.InputSerializer(data=request.query_params.dict())
        given.is_valid(raise_exception=True)
        data = given.validated_data
        fields = request.query_params.get("fields")
        if not fields:
            raise serializers.ValidationError({"fields": ["This field is required."]})
        shape = Shape(data["shape"])
        since, refresh = data["since"], data.get("after") is not None
        if refresh:
            since = max(since, _moment(data["after"]) + MICROSECOND)
            if since >= data["until"]:
                raise SeriesRefused("after must be before until")
        query = series_query_make(
            robot=data["robot"],
            topic=data["topic"],
            fields=fields.split(","),
            since=since,
            until=data["until"],
            points=data["points"],
        )
        if shape == Shape.PATH and len(query.fields) < 2:
            raise SeriesRefused("a path plots two fields, x and y: e.g. position.x,position.y")
        credential, token = caller_credential(request)
        series = series_of(
            viewer=caller_owner(request),
            query=query,
            credential=credential,
            token=token,
            refresh=refresh,
        )
        # A gap no deletion explains is told to the robot's owner, once per gap.
        records_missing_alerts_raise(series.completeness)
        thinned = series_thinned(series.points, points=query.points, shape=shape)
        return Response(
            series.as_json() | {"points": thinned.rows, "shape": shape, "method": thinned.method}
        )


def _moment(seconds: Decimal) -> datetime:
    """Unix seconds (to the microsecond, as the points' t) as a time."""
    return EPOCH + timedelta(microseconds=int(seconds * 1_000_000))
