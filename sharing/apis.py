"""REST API v1 of sharing: uploads from robots, records, integrity-checked content, grants.

One view per route; each validates with its nested serializers, calls one service or
selector, and answers. Refusals are `sharing.errors` (and DRF's), mapped to HTTP in
`core.api_errors`. Who may call what is `accounts.authentication.OwnerCredential`: a robot
token uploads and reads its own uploads' status; everything else needs the owner (a session,
or an owner API token with the `read` or `share` scope).
"""

import base64
import binascii
import contextlib
import uuid
from typing import Any

from django.core.validators import ProhibitNullCharactersValidator, RegexValidator
from django.db.models import QuerySet
from django.http import StreamingHttpResponse
from django.urls import reverse
from django.utils import timezone
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import (
    OpenApiParameter,
    OpenApiResponse,
    PolymorphicProxySerializer,
    extend_schema,
    extend_schema_field,
)
from rest_framework import serializers, status
from rest_framework.pagination import LimitOffsetPagination
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.throttling import BaseThrottle
from rest_framework.views import APIView

from accounts.authentication import (
    OwnerCredential,
    RobotUploadRateThrottle,
    caller_owner,
    caller_owner_token,
    caller_robot,
)
from accounts.lastseen import seen_ago_text
from accounts.models import OwnerToken
from accounts.selectors import KEY_ID_HEADER, owner_key_current_id
from chainworker.services import chain_client
from core.api_errors import ErrorSerializer, error_responses
from sharing.access_log import access_log_redacted, access_outcomes
from sharing.cache import envelope_fetch
from sharing.deletion import record_delete
from sharing.errors import (
    NOT_VISIBLE,
    ExportNotFound,
    NotAnchoredYet,
    RecordNotFound,
    RobotNotFound,
)
from sharing.exports.create import export_create, export_rebuild
from sharing.exports.download import export_current, export_download
from sharing.exports.selection import export_count
from sharing.models import Access, Credential, Export, Grant, Record, Verdict
from sharing.robot_status import RobotActivity, robot_activity, robot_of_owner
from sharing.selection import MAX_SELECTED_ROBOTS, MAX_SELECTED_TOPICS, MAX_TOPIC_LENGTH
from sharing.selectors import (
    ACCESS_LOG_DIRECTIONS,
    ACCESS_LOG_INCOMING,
    RECORD_FILTER_STATUSES,
    access_list_access_log,
    access_list_filtered,
    export_list_of,
    grant_list_given,
    grant_list_received,
    record_list_filtered,
    record_list_uploaded_by,
    record_list_visible_to,
    record_proof,
)
from sharing.series import (
    DEFAULT_POINTS,
    MAX_FIELDS,
    MAX_POINTS,
    series_of,
    series_query_make,
)
from sharing.services import (
    GRANT_MADE_WITH,
    GrantTerms,
    grant_create,
    grant_revoke,
    grant_terms_change,
    grant_terms_make,
    owner_resolve,
    record_create_batch,
)
from sharing.verification.opening import record_open, record_reseal_for
from sharing.verification.signature import record_signature

# Envelopes in one upload at most; the body size limit (413) bounds the bytes.
MAX_ENVELOPES_PER_UPLOAD = 1000
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
_RECORD_ID = OpenApiParameter(
    "record_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the record's id"
)


# --- fields and serializers shared by the views ----------------------------------------------


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


class RecordOutputSerializer(serializers.Serializer):
    class Meta:
        ref_name = "Record"

    id = serializers.UUIDField()
    owner = serializers.CharField(source="owner.user.username")
    owner_address = serializers.CharField(source="owner.eoa_address")
    robot = serializers.UUIDField(source="robot_id")
    robot_name = serializers.CharField(source="robot.name")
    topic = serializers.CharField()
    type = serializers.CharField(source="data_type", help_text="ROS message type")
    seq = serializers.IntegerField()
    captured_at = serializers.DateTimeField()
    size = serializers.IntegerField(help_text="envelope bytes")
    digest = serializers.CharField(help_text="SM3 of the envelope as hex, as anchored on chain")
    key_id = serializers.CharField(help_text="the owner key it is sealed under, hex")
    signer = NullIfBlankCharField(
        help_text=(
            "the robot key that signed it (SM3 of its SM2 public key, hex), checked at upload "
            "and at every view; null for an unsigned record (a robot added by hand)"
        )
    )
    status = serializers.ChoiceField(
        choices=Record.Status.choices, help_text="anchoring: pending, anchored or failed"
    )
    tx_hash = NullIfBlankCharField(help_text="the anchoring transaction, once anchored")
    block_number = serializers.IntegerField(allow_null=True)
    anchored_at = serializers.DateTimeField(allow_null=True)
    failure_reason = NullIfBlankCharField(
        help_text="why anchoring failed, or why a pending record waits (e.g. for gas)"
    )
    tampered_at = serializers.DateTimeField(
        allow_null=True, help_text="when a view found the stored data changed, if ever"
    )
    created_at = serializers.DateTimeField(help_text="when the portal received it")
    deleted_at = serializers.DateTimeField(
        allow_null=True,
        help_text="when it was deleted (its content is gone: 410), or null; listed only with "
        "`?status=deleted`",
    )
    deleted_by = serializers.CharField(
        source="deleted_by.username",
        allow_null=True,
        default=None,
        help_text="who deleted it; null for a retention policy or a live record",
    )
    deletion_reason = NullIfBlankCharField(
        help_text="`owner`, `retention` (the robot's retention policy) or `account` (with "
        "its owner's account); null while live"
    )


class GrantScopeSerializer(serializers.Serializer):
    class Meta:
        ref_name = "GrantScope"

    robots = serializers.ListField(
        child=serializers.UUIDField(), source="scope_robots", help_text="robot ids; [] = all"
    )
    topics = serializers.ListField(
        child=serializers.CharField(), source="scope_topics", help_text="topics; [] = all"
    )
    since = serializers.DateTimeField(
        source="scope_since", allow_null=True, help_text="captured at or after; null = no start"
    )
    until = serializers.DateTimeField(
        source="scope_until", allow_null=True, help_text="captured before; null = no end"
    )
    commitment = serializers.CharField(
        source="scope_commitment_hex",
        help_text="SM3 of the scope's canonical bytes (docs/grants.md) as the chain holds it, "
        "hex; 64 zeros for all records",
    )


class GrantOutputSerializer(serializers.Serializer):
    class Meta:
        ref_name = "Grant"

    owner = serializers.CharField(source="owner.user.username")
    owner_address = serializers.CharField(source="owner.eoa_address")
    grantee = serializers.CharField(source="grantee.user.username")
    grantee_address = serializers.CharField(source="grantee.eoa_address")
    status = serializers.ChoiceField(
        choices=Grant.Status.choices,
        help_text="pending (on chain soon), active, revoking, revoked or failed",
    )
    grant_tx = NullIfBlankCharField()
    grant_block = serializers.IntegerField(allow_null=True)
    revoke_tx = NullIfBlankCharField()
    revoke_block = serializers.IntegerField(allow_null=True)
    created_at = serializers.DateTimeField()
    updated_at = serializers.DateTimeField()
    made_with = serializers.ChoiceField(
        choices=GRANT_MADE_WITH,
        help_text="the credential that made the grant: a browser session, an owner API "
        "token, or an operator's command",
    )
    scope = GrantScopeSerializer(source="*", help_text="which records the grant covers")
    expires_at = serializers.DateTimeField(
        allow_null=True, help_text="from then on the grant gives no access; null = never"
    )
    expired = serializers.BooleanField(source="is_expired", help_text="its expiry has passed")


class GrantTermsInputSerializer(serializers.Serializer):
    """The optional terms of a grant: leave them all out for all records, without expiry."""

    class Meta:
        ref_name = "GrantTerms"

    robots = serializers.ListField(
        child=serializers.UUIDField(),
        required=False,
        max_length=MAX_SELECTED_ROBOTS,
        help_text="only these robots' records (ids of your robots); default: all robots",
    )
    topics = serializers.ListField(
        child=TextField(max_length=MAX_TOPIC_LENGTH),
        required=False,
        max_length=MAX_SELECTED_TOPICS,
        help_text="only these topics' records; default: all topics",
    )
    since = serializers.DateTimeField(
        required=False, allow_null=True, help_text="only records captured at or after (ISO 8601)"
    )
    until = serializers.DateTimeField(
        required=False, allow_null=True, help_text="only records captured before (ISO 8601)"
    )
    expires_at = serializers.DateTimeField(
        required=False,
        allow_null=True,
        help_text="the grant gives no access from then on (ISO 8601, at least 5 minutes "
        "ahead, whole seconds); default: never",
    )

    def terms_for(self, owner: Any) -> GrantTerms:
        data = self.validated_data
        return grant_terms_make(
            owner=owner,
            robots=data.get("robots", ()),
            topics=data.get("topics", ()),
            since=data.get("since"),
            until=data.get("until"),
            expires_at=data.get("expires_at"),
        )


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


class IsRobot(BasePermission):
    message = "uploads need a robot token: `Authorization: Token <key>`"

    def has_permission(self, request: Request, view: APIView) -> bool:
        return caller_robot(request) is not None


# --- records ---------------------------------------------------------------------------------


class RecordsApi(APIView):
    """`GET /api/v1/records/`: what the caller may read; `POST`: a robot's upload."""

    pagination_class = RecordPagination

    class SingleInputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordUploadOne"

        envelope = Base64EnvelopeField(help_text="one envelope v1, base64")

    class BatchInputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordUploadBatch"

        envelopes = serializers.ListField(
            child=Base64EnvelopeField(),
            min_length=1,
            max_length=MAX_ENVELOPES_PER_UPLOAD,
            help_text="envelopes v1, base64, in increasing seq order; stored all or none",
        )

    class UploadOutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordUploaded"

        id = serializers.UUIDField()
        digest = serializers.CharField(help_text="SM3 of the envelope, hex")
        status = serializers.ChoiceField(choices=Record.Status.choices)
        seq = serializers.IntegerField()

    class FilterSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordFilter"

        topic = TextField(required=False, max_length=MAX_TOPIC_LENGTH)
        type = TextField(required=False, max_length=255, help_text="ROS type", source="data_type")
        status = serializers.ChoiceField(
            choices=RECORD_FILTER_STATUSES,
            required=False,
            help_text="anchoring status, or `tampered`: a view found the stored data changed",
        )
        since = serializers.DateTimeField(
            required=False, help_text="captured at or after (ISO 8601)"
        )
        until = serializers.DateTimeField(
            required=False, help_text="captured before, not at (ISO 8601): [since, until)"
        )
        owner = TextField(
            required=False, max_length=MAX_OWNER_IDENTIFIER, help_text="owner's username"
        )
        robot = serializers.UUIDField(required=False, help_text="robot id")

    def get_permissions(self) -> list[BasePermission]:
        if self.request.method == "POST":
            return [IsAuthenticated(), IsRobot()]
        return [IsAuthenticated(), OwnerCredential(READ, "list records", robots=True)]

    def get_throttles(self) -> list[BaseThrottle]:
        return [*super().get_throttles(), RobotUploadRateThrottle()]

    @extend_schema(
        operation_id="records_list",
        summary="Records the caller may read: its own and those shared with it",
        description=(
            "For the owner (a session, or an owner API token with the `read` scope): its own "
            "records and those shared with it. For a robot token: that robot's own uploads."
        ),
        parameters=[FilterSerializer],
        responses={
            200: RecordOutputSerializer(many=True),
            **error_responses(
                400,
                401,
                403,
                e403="`insufficient_scope`: an owner API token without the `read` scope",
            ),
        },
    )
    def get(self, request: Request) -> Response:
        # A plain mapping, not form semantics: `?type=` is refused rather than ignored.
        filters = self.FilterSerializer(data=request.query_params.dict())
        filters.is_valid(raise_exception=True)
        visible = _records_of_caller(request)
        records = record_list_filtered(visible, **filters.validated_data)
        paginator = self.pagination_class()
        page = paginator.paginate_queryset(records, request, view=self)
        return paginator.get_paginated_response(RecordOutputSerializer(page, many=True).data)

    @extend_schema(
        operation_id="records_upload",
        summary="Upload envelopes (robot token only)",
        description=(
            "Each envelope must parse, name this robot and its owner in its header, be sealed "
            "under the owner's current key (or one rotated within the last hour), and carry a "
            "seq above every earlier one of this robot. A batch is stored all or nothing. "
            "`envelope` answers one result, `envelopes` a list in the same order."
        ),
        auth=ROBOT_ONLY,
        request=PolymorphicProxySerializer(
            component_name="RecordUpload",
            serializers=[SingleInputSerializer, BatchInputSerializer],
            resource_type_field_name=None,
        ),
        responses={
            201: PolymorphicProxySerializer(
                component_name="RecordUploadResult",
                serializers=[UploadOutputSerializer, UploadOutputSerializer(many=True)],
                resource_type_field_name=None,
                many=False,
            ),
            **error_responses(
                400,
                401,
                403,
                409,
                413,
                415,
                503,
                e400="`invalid_request` (not JSON, not base64, both or neither of "
                "`envelope`/`envelopes`), `invalid_envelope` (does not parse, seq not "
                "increasing within the batch)",
                e403="`permission_denied` (not a robot token), `header_mismatch` (another "
                "owner or robot), `unknown_key` (not the owner's current key), "
                "`forged_envelope` (does not open under the owner's key)",
                e409="`replayed_sequence`: these very envelopes are stored already (a lost 201); "
                "`sequence_conflict`: a seq not above the robot's last one, with other data "
                "(the owner is told: a robot that lost its state, or a stolen token and key); "
                "`identity_check_failed`: the owner's key commitment on chain differs from "
                "the key the portal holds (an operator must look)",
                e503="`storage_unavailable`: the upload could not be stored durably (nothing "
                "was kept), or its stored rows could not be synced to disk; send it again "
                "after `Retry-After` seconds (a resend of what was stored is answered "
                "`replayed_sequence`)",
            ),
        },
    )
    def post(self, request: Request) -> Response:
        robot = caller_robot(request)
        batch = isinstance(request.data, dict) and "envelopes" in request.data
        input_class = self.BatchInputSerializer if batch else self.SingleInputSerializer
        if batch and "envelope" in request.data:
            raise serializers.ValidationError("send either `envelope` or `envelopes`, not both")
        upload = input_class(data=request.data)
        upload.is_valid(raise_exception=True)
        if batch:
            envelopes = upload.validated_data["envelopes"]
        else:
            envelopes = [upload.validated_data["envelope"]]
        records = record_create_batch(robot=robot, envelopes=envelopes)
        results = self.UploadOutputSerializer(records, many=True).data
        return Response(results if batch else results[0], status=status.HTTP_201_CREATED)

    def finalize_response(
        self, request: Request, response: Response, *args: Any, **kwargs: Any
    ) -> Response:
        """Every answer to a paired robot's upload, refusals included, names the owner's current
        key: a robot that sees another id fetches the new key (`/api/v1/robot-key/`). Robots
        set up by hand cannot fetch it, and their uploads pay no query for it."""
        robot = caller_robot(request) if request.method == "POST" else None
        if robot is not None and robot.public_key:
            current = owner_key_current_id(robot.owner_id)
            if current:
                response[KEY_ID_HEADER] = current
        return super().finalize_response(request, response, *args, **kwargs)


def _record_uuid(record_id: str) -> uuid.UUID:
    try:
        return uuid.UUID(record_id)
    except ValueError:
        raise RecordNotFound(NOT_VISIBLE) from None


def _records_of_caller(request: Request) -> QuerySet[Record]:
    """A robot sees its own uploads; the owner its records and those shared with it."""
    robot = caller_robot(request)
    if robot is not None:
        return record_list_uploaded_by(robot)
    return record_list_visible_to(caller_owner(request))


def _refuse_unseen(request: Request, record_id: uuid.UUID) -> None:
    """A record the caller may not see: 404 whether it exists or not, outside a grant's scope
    or not (nothing tells it exists)."""
    raise RecordNotFound(NOT_VISIBLE)


class RecordDetailApi(APIView):
    """`GET /api/v1/records/{id}/`: metadata and anchoring status; `DELETE`: delete it."""

    def get_permissions(self) -> list[BasePermission]:
        if self.request.method == "DELETE":
            return [IsAuthenticated(), OwnerCredential(DELETE, "delete a record")]
        return [IsAuthenticated(), OwnerCredential(READ, "read a record", robots=True)]

    @extend_schema(
        operation_id="records_detail",
        summary="A record's metadata and anchoring status",
        description=(
            "For the owner or a grantee (a session, or an owner API token with the `read` "
            "scope), and for the robot that uploaded it (its token)."
        ),
        parameters=[_RECORD_ID],
        responses={
            200: RecordOutputSerializer,
            **error_responses(
                401,
                403,
                404,
                e403="`insufficient_scope`: an owner API token without the `read` scope",
                e404="`not_found`: no such record, not shared with you, or (robot token) not "
                "uploaded by this robot",
            ),
        },
    )
    def get(self, request: Request, record_id: str) -> Response:
        record_uuid = _record_uuid(record_id)
        record = (
            _records_of_caller(request).select_related("deleted_by").filter(pk=record_uuid).first()
        )
        if record is None:
            _refuse_unseen(request, record_uuid)
        return Response(RecordOutputSerializer(record).data)

    @extend_schema(
        operation_id="records_delete",
        summary="Delete one of your records",
        description=(
            "The record becomes a tombstone at once (its content answers 410 `record_deleted`) "
            "and its ciphertext is removed from storage and cache; its metadata, its digest on "
            "chain and its proof stay. Only anchored records are deleted. Deleting a deleted "
            "record again answers the same. The owner only: a session, or an owner API token "
            "with the `delete` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[_RECORD_ID],
        responses={
            200: OpenApiResponse(RecordOutputSerializer, description="the tombstone"),
            **error_responses(
                401,
                403,
                404,
                409,
                e403="`not_record_owner`: shared with you, not yours; "
                + ROBOT_REFUSED.format(scope="delete"),
                e404="`not_found`: no such record, or not shared with you",
                e409="`not_anchored_yet`: delete it once it is anchored",
            ),
        },
    )
    def delete(self, request: Request, record_id: str) -> Response:
        record = record_delete(
            owner=caller_owner(request), record_id=_record_uuid(record_id), actor=request.user
        )
        return Response(RecordOutputSerializer(record).data)


class RecordContentApi(APIView):
    """`GET /api/v1/records/{id}/content/`: integrity-checked, re-sealed for the caller."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read a record's content")]

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordContent"

        id = serializers.UUIDField()
        verified = serializers.BooleanField(help_text="always true: otherwise the answer is 409")
        digest = serializers.CharField(help_text="SM3 of the stored envelope, equal on chain")
        block_number = serializers.IntegerField(
            allow_null=True, help_text="the block the check was made against"
        )
        envelope = Base64EnvelopeField(
            help_text="the content re-sealed under the caller's own current key, base64"
        )

    @extend_schema(
        operation_id="records_content",
        summary="The record's content, after checking it against the chain",
        description=(
            "The stored envelope is hashed again and compared with the digest on chain; access "
            "needs the owner, or a grant that is live in the portal and on chain. The content "
            "comes back sealed under the caller's own current key, with the same header. "
            "Needs the owner or grantee: a session, or an owner API token with the `read` "
            "scope; never a robot token."
        ),
        auth=OWNER_ONLY,
        parameters=[_RECORD_ID],
        responses={
            200: OutputSerializer,
            **error_responses(
                401,
                403,
                404,
                409,
                410,
                503,
                e403=ROBOT_REFUSED.format(scope="read"),
                e409="`integrity_check_failed`: the stored data differs from the chain; "
                "`not_anchored_yet`: try again shortly; `identity_check_failed`: the owner's "
                "key commitment on chain differs from the key the portal holds",
            ),
        },
    )
    def get(self, request: Request, record_id: str) -> Response:
        viewer = caller_owner(request)
        credential, token = _caller_credential(request)
        opened = record_open(
            record_id=_record_uuid(record_id), viewer=viewer, credential=credential, token=token
        )
        resealed = record_reseal_for(opened=opened, viewer=viewer)
        data = {
            "id": opened.record.id,
            "verified": True,
            "digest": opened.verdict.chain_digest,
            "block_number": opened.verdict.block_number,
            "envelope": resealed,
        }
        return Response(self.OutputSerializer(data).data)


def _caller_credential(request: Request) -> tuple[str, OwnerToken | None]:
    """The owner's credential behind a request, as the access log records it: an owner API
    token (with the token), else the browser session."""
    token = caller_owner_token(request)
    return (Credential.SESSION if token is None else Credential.TOKEN), token


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
            help_text="points answered at most (downsampled by min/max per bucket)",
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
                "not anchored yet, no access on chain): never plotted",
            },
            "without_values": {
                "type": "integer",
                "description": "verified records holding none of the fields as a number",
            },
        },
    }

    @extend_schema(
        operation_id="records_series",
        summary="Numeric fields of a robot's topic over time, every record checked",
        description=(
            "Every record of the robot's topic captured in [since, until) that the caller may "
            "read (its own, or within a live grant's scope) is checked against the chain like "
            "a content read; the verified ones' fields are answered, downsampled to at most "
            "`points` rows by keeping each field's lowest and highest value per slice of time "
            "(never by skipping records). The whole answer is one line of the access log "
            "(kind `plot`). A session or an owner API token with the `read` scope."
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
                e400="`invalid_request` (a parameter missing or malformed), `invalid_series` "
                "(too many fields, a range too long or holding too many records)",
                e403=ROBOT_REFUSED.format(scope="read"),
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
        query = series_query_make(
            robot=data["robot"],
            topic=data["topic"],
            fields=fields.split(","),
            since=data["since"],
            until=data["until"],
            points=data["points"],
        )
        credential, token = _caller_credential(request)
        series = series_of(
            viewer=caller_owner(request), query=query, credential=credential, token=token
        )
        return Response(series.as_json())


class ProofAnchorSerializer(serializers.Serializer):
    class Meta:
        ref_name = "ProofAnchor"

    chain_id = serializers.IntegerField()
    contract = serializers.CharField(help_text="the AuthROS contract's address")
    sender = serializers.CharField(help_text="the account that anchored it (the owner's)")
    tx = serializers.CharField()
    block = serializers.IntegerField(allow_null=True)


class ProofSignatureSerializer(serializers.Serializer):
    class Meta:
        ref_name = "ProofSignature"

    signer = serializers.CharField(help_text="SM3 of the robot's public key x||y, hex")
    public_key = serializers.CharField(help_text="the robot's SM2 public key, 04||x||y hex")
    sig = serializers.CharField(help_text="the SM2 signature r||s, hex (DESIGN.md Provenance)")
    key_owner = serializers.CharField(
        allow_null=True, help_text="robotKeyOf(signer).owner: the EOA that registered the key"
    )
    key_added_block = serializers.IntegerField(allow_null=True)
    key_revoked_block = serializers.IntegerField(allow_null=True, help_text="null: live")


class RecordProofApi(APIView):
    """`GET /api/v1/records/{id}/proof/`: the record's anchoring proof."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read a record's proof")]

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RecordProof"

        record = serializers.UUIDField()
        owner = serializers.CharField(help_text="the owner's EOA")
        digest = serializers.CharField(help_text="SM3 of the envelope, 0x hex")
        mode = serializers.ChoiceField(choices=["root", "record"])
        leaf_index = serializers.IntegerField()
        tree_size = serializers.IntegerField()
        path = serializers.ListField(
            child=serializers.CharField(), help_text="the audit path, leaf up (RFC 9162 2.1.3)"
        )
        root = serializers.CharField(help_text="the anchored root (record mode: the digest)")
        anchor = ProofAnchorSerializer()
        envelope = serializers.CharField(
            allow_null=True,
            help_text="the anchored envelope as stored, base64; null once the record is deleted",
        )
        signature = ProofSignatureSerializer(
            allow_null=True, help_text="the robot's signature; null for an unsigned record"
        )

    @extend_schema(
        operation_id="records_proof",
        summary="The record's anchoring proof, to check it without the portal",
        description=(
            "Root mode: SM3 the envelope, make the leaf SM3(0x00 || owner || record id || "
            "digest), fold the path (RFC 9162 2.1.3.2) to the root, and call "
            "rootOf(sender, root) on the contract: its size must be tree_size. Record mode: "
            "dataQueryOf(owner, record id) holds the digest. `envelope` is the stored envelope and "
            "`signature` the robot's: SM3 of public_key must be signer, the SM2 signature over "
            "the record's plaintext must hold (DESIGN.md Provenance), and robotKeyOf(signer) "
            "must name the owner, added at or before the anchoring block and not revoked by "
            "then. For the owner or a grantee (a session, or an owner API token with the `read` "
            "scope)."
        ),
        auth=OWNER_ONLY,
        parameters=[_RECORD_ID],
        responses={
            200: OutputSerializer,
            **error_responses(
                401,
                403,
                404,
                409,
                e403=ROBOT_REFUSED.format(scope="read"),
                e404="`not_found`: no such record, or not shared with you",
                e409="`not_anchored_yet`: the record is not on chain yet",
            ),
        },
    )
    def get(self, request: Request, record_id: str) -> Response:
        record = (
            record_list_visible_to(caller_owner(request))
            .select_related("owner", "anchor_root")
            .filter(pk=_record_uuid(record_id))
            .first()
        )
        if record is None:
            _refuse_unseen(request, _record_uuid(record_id))
        if record.status != Record.Status.ANCHORED:
            raise NotAnchoredYet("the record is not anchored yet; try again shortly")
        client = chain_client()
        proof = record_proof(record, chain_id=client.chain_id, contract=client.address)
        proof["envelope"] = proof["signature"] = None
        # A deleted record's envelope is gone (its proof stays); one removed behind the
        # portal's back too: the check at the next view says so.
        with contextlib.suppress(FileNotFoundError):
            if not record.is_deleted:
                data, _source = envelope_fetch(record)
                proof["envelope"] = base64.b64encode(data).decode("ascii")
                proof["signature"] = record_signature(record, data, client)
        return Response(self.OutputSerializer(proof).data)


# --- grants ----------------------------------------------------------------------------------


class GrantsApi(APIView):
    """`GET /api/v1/grants/`: grants given and received; `POST`: grant access."""

    class ListOutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "GrantList"

        given = GrantOutputSerializer(many=True, help_text="by the caller's owner, newest first")
        received = GrantOutputSerializer(many=True, help_text="to the caller's owner")

    class InputSerializer(GrantTermsInputSerializer):
        class Meta:
            ref_name = "GrantRequest"

        grantee = TextField(
            max_length=MAX_OWNER_IDENTIFIER, help_text="the grantee's username or 0x address"
        )

    def get_permissions(self) -> list[BasePermission]:
        action = "grant access" if self.request.method == "POST" else "list grants"
        return [IsAuthenticated(), OwnerCredential(SHARE, action)]

    @extend_schema(
        operation_id="grants_list",
        summary="Grants given and received",
        description="A session, or an owner API token with the `share` scope.",
        auth=OWNER_ONLY,
        responses={
            200: ListOutputSerializer,
            **error_responses(401, 403, e403=ROBOT_REFUSED.format(scope="share")),
        },
    )
    def get(self, request: Request) -> Response:
        owner = caller_owner(request)
        data = {"given": grant_list_given(owner), "received": grant_list_received(owner)}
        return Response(self.ListOutputSerializer(data).data)

    @extend_schema(
        operation_id="grants_create",
        summary="Let another owner read your records",
        description=(
            "Takes effect in the portal once `authorityGrant` is confirmed on chain. A session, "
            "or an owner API token with the `share` scope; the grant records which. Optional "
            "terms limit it to some robots, topics and a capture-time window, and let it "
            "expire (`authorityGrantScoped` then, with the scope's SM3 commitment: "
            'docs/grants.md); `{"grantee": ...}` alone grants all records, without expiry.'
        ),
        auth=OWNER_ONLY,
        request=InputSerializer,
        responses={
            201: GrantOutputSerializer,
            **error_responses(
                400,
                401,
                403,
                404,
                409,
                415,
                e400="`invalid_request`, `invalid_grant_terms` (a robot not yours, a window "
                "ending before it starts, an expiry less than 5 minutes ahead), or `self_grant`",
                e403=ROBOT_REFUSED.format(scope="share"),
                e404="`owner_not_found`: no owner with that username or address",
                e409="`already_granted`, `revocation_pending` (your revocation of that owner is "
                "not on chain yet: try again in a few seconds), `not_registered_yet` (you), "
                "`grantee_not_registered`",
            ),
        },
    )
    def post(self, request: Request) -> Response:
        owner = caller_owner(request)
        payload = self.InputSerializer(data=request.data)
        payload.is_valid(raise_exception=True)
        terms = payload.terms_for(owner)
        grantee = owner_resolve(payload.validated_data["grantee"])
        token = caller_owner_token(request)
        grant = grant_create(
            owner=owner,
            grantee=grantee,
            made_with="session" if token is None else "token",
            made_with_token=token,
            terms=terms,
        )
        return Response(GrantOutputSerializer(grant).data, status=status.HTTP_201_CREATED)


_GRANTEE = OpenApiParameter(
    "grantee",
    OpenApiTypes.STR,
    OpenApiParameter.PATH,
    description="the grantee's username or 0x address",
)


class GrantRevokeApi(APIView):
    """`DELETE /api/v1/grants/{grantee}/`: take access away at once; `PATCH`: change the
    grant's terms (a new transaction on chain)."""

    def get_permissions(self) -> list[BasePermission]:
        action = "change a grant" if self.request.method == "PATCH" else "revoke a grant"
        return [IsAuthenticated(), OwnerCredential(SHARE, action)]

    @extend_schema(
        operation_id="grants_change",
        summary="Change what a grant covers, or its expiry",
        description=(
            "The new terms replace the old ones (leave them all out for all records, without "
            "expiry). The portal enforces them at once; the grant is `pending` until "
            "`authorityGrantScoped` confirms them on chain, and gives no access meanwhile. "
            "A session, or an owner API token with the `share` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[_GRANTEE],
        request=GrantTermsInputSerializer,
        responses={
            200: OpenApiResponse(GrantOutputSerializer, description="now `pending`"),
            **error_responses(
                400,
                401,
                403,
                404,
                415,
                e400="`invalid_request`, `invalid_grant_terms`",
                e403=ROBOT_REFUSED.format(scope="share")
                + "; `token_cannot_widen`: an API token may narrow a grant, but widen only a "
                "grant it made and nothing else changed since",
                e404="`owner_not_found`, or `no_grant`: nothing live to change",
            ),
        },
    )
    def patch(self, request: Request, grantee: str) -> Response:
        owner = caller_owner(request)
        payload = GrantTermsInputSerializer(data=request.data)
        payload.is_valid(raise_exception=True)
        terms = payload.terms_for(owner)
        token = caller_owner_token(request)
        grant = grant_terms_change(
            owner=owner,
            grantee=owner_resolve(grantee),
            terms=terms,
            made_with="session" if token is None else "token",
            made_with_token=token,
        )
        return Response(GrantOutputSerializer(grant).data)

    @extend_schema(
        operation_id="grants_revoke",
        summary="Revoke a grant",
        description=(
            "Refused by the portal at once; `authorityRevoke` follows on chain. A session, or "
            "an owner API token with the `share` scope."
        ),
        auth=OWNER_ONLY,
        parameters=[_GRANTEE],
        responses={
            200: OpenApiResponse(GrantOutputSerializer, description="now `revoking`"),
            **error_responses(
                401,
                403,
                404,
                e403=ROBOT_REFUSED.format(scope="share"),
                e404="`owner_not_found`, or `no_grant`: nothing live to revoke",
            ),
        },
    )
    def delete(self, request: Request, grantee: str) -> Response:
        owner = caller_owner(request)
        token = caller_owner_token(request)
        grant = grant_revoke(
            owner=owner,
            grantee=owner_resolve(grantee),
            made_with="session" if token is None else "token",
            made_with_token=token,
        )
        return Response(GrantOutputSerializer(grant).data)


# --- the access log --------------------------------------------------------------------------


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
        since = serializers.DateTimeField(required=False, help_text="viewed at or after")
        until = serializers.DateTimeField(
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


class ExportOutputSerializer(serializers.Serializer):
    class Meta:
        ref_name = "Export"

    id = serializers.UUIDField()
    status = serializers.ChoiceField(
        choices=Export.Status.choices,
        help_text="queued, running, done, failed, expired or withdrawn",
    )
    selection = serializers.DictField(help_text="robots, topics, since, until as asked")
    total = serializers.IntegerField(help_text="records in the selection")
    processed = serializers.IntegerField(help_text="records checked against the chain so far")
    exported = serializers.IntegerField(help_text="records that passed and are in the file")
    excluded = serializers.ListField(
        child=serializers.DictField(),
        help_text="records left out: `record`, `topic`, `captured_at`, `reason` "
        "(`integrity_check_failed`, `access_denied`, `not_anchored_yet`, ...)",
    )
    percent = serializers.IntegerField(help_text="records checked, in percent")
    error = NullIfBlankCharField(
        help_text="why it failed, or why it was withdrawn (status `withdrawn`: the requester "
        "may no longer view every record in it; its files are removed)"
    )
    mcap_size = serializers.IntegerField()
    mcap_sm3 = NullIfBlankCharField(help_text="SM3 of the MCAP file, hex")
    bundle_size = serializers.IntegerField()
    mcap_url = serializers.SerializerMethodField()
    bundle_url = serializers.SerializerMethodField()
    created_at = serializers.DateTimeField()
    finished_at = serializers.DateTimeField(allow_null=True)
    expires_at = serializers.DateTimeField(help_text="its files are removed then")

    def get_mcap_url(self, export: Export) -> str | None:
        return _export_file_url(export, "mcap")

    def get_bundle_url(self, export: Export) -> str | None:
        return _export_file_url(export, "bundle")


def _export_file_url(export: Export, part: str) -> str | None:
    if export.status != Export.Status.DONE:
        return None
    return reverse("api-v1:export-file", args=[export.pk, part])


class ExportSelectionSerializer(serializers.Serializer):
    """What to export: robots and topics (empty: all) and a capture-time window."""

    class Meta:
        ref_name = "ExportRequest"

    robots = serializers.ListField(
        child=serializers.UUIDField(),
        required=False,
        max_length=MAX_SELECTED_ROBOTS,
        help_text="robot ids (empty or absent: every robot you may view)",
    )
    topics = serializers.ListField(
        child=TextField(max_length=MAX_TOPIC_LENGTH),
        required=False,
        max_length=MAX_SELECTED_TOPICS,
        help_text="topics (empty or absent: every topic)",
    )
    since = serializers.DateTimeField(required=False, help_text="captured at or after")
    until = serializers.DateTimeField(required=False, help_text="captured before")


def _selection_of(data: dict[str, Any]) -> dict[str, Any]:
    return {
        "robots": data.get("robots", ()),
        "topics": data.get("topics", ()),
        "since": data.get("since"),
        "until": data.get("until"),
    }


class ExportsApi(APIView):
    """`GET /api/v1/exports/`: the caller's exports; `POST`: export a selection."""

    InputSerializer = ExportSelectionSerializer

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "export records")]

    @extend_schema(
        operation_id="exports_list",
        summary="Your exports, newest first",
        auth=OWNER_ONLY,
        responses={
            200: ExportOutputSerializer(many=True),
            **error_responses(401, 403, e403=ROBOT_REFUSED.format(scope="read")),
        },
    )
    def get(self, request: Request) -> Response:
        exports = export_list_of(caller_owner(request))[:50]
        return Response(ExportOutputSerializer(exports, many=True).data)

    @extend_schema(
        operation_id="exports_create",
        summary="Export the verified records of a selection as MCAP, with a proof bundle",
        description=(
            "Runs on a worker: follow it with `GET /api/v1/exports/{id}/`. Only records you may "
            "view (as `GET /api/v1/records/` lists them) and that pass the integrity check on "
            "chain are exported; the others are listed in `excluded`. docs/export.md describes "
            "the MCAP file and the proof bundle."
        ),
        auth=OWNER_ONLY,
        request=InputSerializer,
        responses={
            202: ExportOutputSerializer,
            **error_responses(
                400,
                401,
                403,
                415,
                e400="`invalid_request`, or `invalid_selection`: no record in it, too many "
                "records, or a robot you may not view",
                e403=ROBOT_REFUSED.format(scope="read"),
            ),
        },
    )
    def post(self, request: Request) -> Response:
        payload = self.InputSerializer(data=request.data)
        payload.is_valid(raise_exception=True)
        credential, token = _caller_credential(request)
        export = export_create(
            requester=caller_owner(request),
            credential=credential,
            token=token,
            **_selection_of(payload.validated_data),
        )
        export.refresh_from_db()
        return Response(ExportOutputSerializer(export).data, status=status.HTTP_202_ACCEPTED)


class ExportCountApi(APIView):
    """`GET /api/v1/exports/count/?robots=..&topics=..&since=..&until=..`: how many records a
    selection holds that the caller may view, before exporting it."""

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "ExportCount"

        count = serializers.IntegerField(help_text="records of the selection you may view")
        limit = serializers.IntegerField(help_text="EXPORT_MAX_RECORDS: an export takes at most")
        exportable = serializers.BooleanField()
        refusal = NullIfBlankCharField(help_text="why it would be refused, if it would")

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "count records to export")]

    @extend_schema(
        operation_id="exports_count",
        summary="Count the records of a selection before exporting it",
        auth=OWNER_ONLY,
        parameters=[ExportSelectionSerializer],
        responses={
            200: OutputSerializer,
            **error_responses(
                400,
                401,
                403,
                e400="`invalid_request`, or `invalid_selection`: a robot you may not view",
                e403=ROBOT_REFUSED.format(scope="read"),
            ),
        },
    )
    def get(self, request: Request) -> Response:
        payload = ExportSelectionSerializer(data=request.query_params)
        payload.is_valid(raise_exception=True)
        counted = export_count(
            requester=caller_owner(request), **_selection_of(payload.validated_data)
        )
        answer = {
            "count": counted.count,
            "limit": counted.limit,
            "exportable": not counted.refusal,
            "refusal": counted.refusal,
        }
        return Response(self.OutputSerializer(answer).data)


class ExportRebuildApi(APIView):
    """`POST /api/v1/exports/{id}/rebuild/`: export an export's selection again, under the
    caller's access now (after it was withdrawn or expired)."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "export records")]

    @extend_schema(
        operation_id="exports_rebuild",
        summary="Export an export's selection again, under your access now",
        auth=OWNER_ONLY,
        request=None,
        parameters=[
            OpenApiParameter(
                "export_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the export"
            )
        ],
        responses={
            202: ExportOutputSerializer,
            **error_responses(
                400,
                401,
                403,
                404,
                e400="`invalid_selection`: nothing you may view is in it any more, or too much",
                e404="`not_found`: no export of yours",
            ),
        },
    )
    def post(self, request: Request, export_id: str) -> Response:
        credential, token = _caller_credential(request)
        export = export_rebuild(
            requester=caller_owner(request),
            export_id=export_id,
            credential=credential,
            token=token,
        )
        export.refresh_from_db()
        return Response(ExportOutputSerializer(export).data, status=status.HTTP_202_ACCEPTED)


_EXPORT_ID = OpenApiParameter(
    "export_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the export's id"
)


class ExportDetailApi(APIView):
    """`GET /api/v1/exports/{id}/`: an export's progress and, once done, its files."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "follow an export")]

    @extend_schema(
        operation_id="exports_detail",
        summary="An export's progress",
        auth=OWNER_ONLY,
        parameters=[_EXPORT_ID],
        responses={
            200: ExportOutputSerializer,
            **error_responses(401, 403, 404, e404="`not_found`: no export of yours"),
        },
    )
    def get(self, request: Request, export_id: str) -> Response:
        export = export_current(requester=caller_owner(request), export_id=export_id)
        return Response(ExportOutputSerializer(export).data)


class ExportFileApi(APIView):
    """`GET /api/v1/exports/{id}/mcap/` and `.../bundle/`: the files, for their requester."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "download an export")]

    @extend_schema(
        operation_id="exports_file",
        summary="Download an export's MCAP file (`mcap`) or proof bundle (`bundle`)",
        auth=OWNER_ONLY,
        parameters=[
            _EXPORT_ID,
            OpenApiParameter(
                "part", OpenApiTypes.STR, OpenApiParameter.PATH, enum=["mcap", "bundle"]
            ),
        ],
        responses={
            (200, "application/octet-stream"): OpenApiTypes.BINARY,
            **error_responses(
                401,
                403,
                404,
                409,
                e404="`not_found`: no export of yours",
                e409="`export_not_ready`: still running, or failed",
            ),
            410: OpenApiResponse(
                ErrorSerializer,
                description="`export_expired`: its files are removed; `export_withdrawn`: you "
                "may no longer view every record in it (a grant revoked, expired or narrowed, a "
                "record deleted, an account closed), its files are removed, nothing is sent",
            ),
        },
    )
    def get(self, request: Request, export_id: str, part: str) -> StreamingHttpResponse:
        if part not in ("mcap", "bundle"):
            raise ExportNotFound("an export has two files: mcap and bundle")
        file = export_download(requester=caller_owner(request), export_id=export_id, part=part)
        content_type = "application/json" if part == "bundle" else "application/octet-stream"
        # Decrypted segment by segment as it is sent: never whole in memory, never at rest.
        response = StreamingHttpResponse(file.chunks(), content_type=content_type)
        response["Content-Length"] = str(file.size)
        response["Content-Disposition"] = f'attachment; filename="{file.filename}"'
        response["Cache-Control"] = "no-store, private"
        return response


# --- a robot's status ------------------------------------------------------------------------


class RobotTopicRateSerializer(serializers.Serializer):
    class Meta:
        ref_name = "RobotTopicRate"

    topic = serializers.CharField()
    type = serializers.CharField(source="data_type", help_text="ROS message type")
    last_minute = serializers.IntegerField(help_text="messages captured in the last minute")
    last_hour = serializers.IntegerField(help_text="messages captured in the last hour")
    per_second_minute = serializers.FloatField(help_text="messages per second, last minute")
    per_second_hour = serializers.FloatField(help_text="messages per second, last hour")


class RobotStatusApi(APIView):
    """`GET /api/v1/robots/{id}/status/`: is the robot alive, and what it sends (the robot
    page polls it). Reads no content: nothing is checked against the chain."""

    def get_permissions(self) -> list[BasePermission]:
        return [IsAuthenticated(), OwnerCredential(READ, "read a robot's status")]

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotStatus"

        robot = serializers.UUIDField(source="robot.id")
        name = serializers.CharField(source="robot.name")
        active = serializers.BooleanField(source="robot.is_active", help_text="its token works")
        now = serializers.DateTimeField(help_text="the portal's time of this answer")
        last_seen_at = serializers.DateTimeField(
            allow_null=True, help_text="its newest upload reached the portal then; null: never"
        )
        last_seen = serializers.SerializerMethodField(help_text='e.g. "2 s ago", or "never"')
        last_captured_at = serializers.DateTimeField(
            allow_null=True, help_text="the newest capture time it sent"
        )
        topics = RobotTopicRateSerializer(
            many=True, help_text="topics with messages in the last hour, busiest first"
        )

        def get_last_seen(self, activity: RobotActivity) -> str:
            return seen_ago_text(activity.last_seen_at, now=activity.now)

    @extend_schema(
        operation_id="robots_status",
        summary="A robot's last contact and messages per second per topic",
        description=(
            "When the robot was last heard of, and how many messages of each topic it captured "
            "over the last minute and hour. The robot's owner: a session, or an owner API "
            "token with the `read` scope. Another owner's robot answers 404, as one that does "
            "not exist."
        ),
        auth=OWNER_ONLY,
        parameters=[
            OpenApiParameter(
                "robot_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the robot's id"
            )
        ],
        responses={
            200: OutputSerializer,
            **error_responses(
                401, 403, 404, e403=ROBOT_REFUSED.format(scope="read"), e404="`not_found`"
            ),
        },
    )
    def get(self, request: Request, robot_id: str) -> Response:
        robot = robot_of_owner(caller_owner(request), robot_id)
        if robot is None:
            raise RobotNotFound("no such robot of yours")
        activity = robot_activity(robot, now=timezone.now())
        response = Response(self.OutputSerializer(activity).data)
        response["Cache-Control"] = "no-store, private"
        return response
