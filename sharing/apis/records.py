"""`/api/v1/records/` and `/api/v1/records/{id}/`: robots' uploads, the records the caller
may read (filtered, a page at a time), one record's metadata, and its deletion."""

from typing import Any

from django.db.models import QuerySet
from drf_spectacular.utils import OpenApiResponse, PolymorphicProxySerializer, extend_schema
from rest_framework import serializers, status
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.throttling import BaseThrottle
from rest_framework.views import APIView

from accounts.authentication import (
    OwnerCredential,
    RobotUploadRateThrottle,
    caller_owner,
    caller_robot,
)
from accounts.selectors import KEY_ID_HEADER, owner_key_current_id
from core.api_errors import error_responses
from sharing.apis.fields import (
    DELETE,
    MAX_OWNER_IDENTIFIER,
    OWNER_ONLY,
    READ,
    RECORD_ID,
    ROBOT_ONLY,
    ROBOT_REFUSED,
    Base64EnvelopeField,
    IsRobot,
    NullIfBlankCharField,
    RecordKeysetPagination,
    TextField,
    record_uuid,
    refuse_unseen,
)
from sharing.models import Record
from sharing.selection import MAX_TOPIC_LENGTH
from sharing.selectors.records import (
    RECORD_FILTER_STATUSES,
    record_list_filtered,
    record_list_uploaded_by,
    record_list_visible_to,
)
from sharing.services.deletion import record_delete
from sharing.services.uploads import record_create_batch

# Envelopes in one upload at most; the body size limit (413) bounds the bytes.
MAX_ENVELOPES_PER_UPLOAD = 1000


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


class RecordsApi(APIView):
    """`GET /api/v1/records/`: what the caller may read; `POST`: a robot's upload."""

    pagination_class = RecordKeysetPagination

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
            "seq above every earlier one of this robot. A paired robot's envelopes carry its "
            "signature: v2 (one signature per batch, each record with its place in the batch "
            "and its topic_seq) or v1 (one per envelope, older agents); each distinct batch "
            "signature is verified once. A batch is stored all or nothing. "
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
                "`forged_envelope` (does not open under the owner's key), `signature_refused` "
                "(a paired robot's envelope unsigned, signed by another key, or whose signature "
                "does not hold: for v2, a record that does not fold to its batch's signed root, "
                "or a wrong sig_index or sig_size; the whole upload is refused)",
                e409="`replayed_sequence`: these very envelopes are stored already (a lost 201); "
                "`sequence_conflict`: a seq not above the robot's last one, with other data "
                "(the owner is told: a robot that lost its state, or a stolen token and key); "
                "`topic_seq_reused`: a v2 record's topic_seq its robot's key used already for "
                "the topic (a record stored before, deleted or not, or another of the upload): "
                "nothing is stored and the owner is told; "
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


def _records_of_caller(request: Request) -> QuerySet[Record]:
    """A robot sees its own uploads; the owner its records and those shared with it."""
    robot = caller_robot(request)
    if robot is not None:
        return record_list_uploaded_by(robot)
    return record_list_visible_to(caller_owner(request))


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
        parameters=[RECORD_ID],
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
        wanted = record_uuid(record_id)
        record = _records_of_caller(request).select_related("deleted_by").filter(pk=wanted).first()
        if record is None:
            refuse_unseen(request, wanted)
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
        parameters=[RECORD_ID],
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
            owner=caller_owner(request), record_id=record_uuid(record_id), actor=request.user
        )
        return Response(RecordOutputSerializer(record).data)
