"""`/api/v1/exports/...`: exporting a selection of records as MCAP with a proof bundle:
the caller's exports, creating one, counting a selection first, following one, rebuilding
one under the caller's access now, and downloading its files."""

from typing import ClassVar

from django.http import StreamingHttpResponse
from django.urls import reverse
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import serializers, status
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from core.api_errors import ErrorSerializer, error_responses
from sharing.apis.fields import (
    OWNER_ONLY,
    READ,
    ROBOT_REFUSED,
    NullIfBlankCharField,
    RecordSelectionSerializer,
    caller_credential,
)
from sharing.errors import ExportNotFound
from sharing.exports.create import export_create, export_rebuild
from sharing.exports.download import export_current, export_download
from sharing.exports.selection import export_count
from sharing.models import Export
from sharing.selectors.exports import export_list_of


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


class ExportSelectionSerializer(RecordSelectionSerializer):
    """What to export: robots and topics (empty: all) and a capture-time window."""

    class Meta:
        ref_name = "ExportRequest"

    selection_help: ClassVar[dict[str, str]] = {
        "robots": "robot ids (empty or absent: every robot you may view)",
        "topics": "topics (empty or absent: every topic)",
        "since": "captured at or after",
        "until": "captured before",
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
        credential, token = caller_credential(request)
        export = export_create(
            requester=caller_owner(request),
            credential=credential,
            token=token,
            **payload.selection(),
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
        counted = export_count(requester=caller_owner(request), **payload.selection())
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
        credential, token = caller_credential(request)
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
