"""`/api/v1/records/{id}/content/`: a record's content, checked against the chain
(`record_open`) and re-sealed under the caller's own current key."""

from drf_spectacular.utils import extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from core.api_errors import error_responses
from sharing.apis.fields import (
    CHECKS_OVER_BUDGET,
    OWNER_ONLY,
    READ,
    RECORD_ID,
    ROBOT_REFUSED,
    Base64EnvelopeField,
    caller_credential,
    record_uuid,
)
from sharing.verification.opening import record_open, record_reseal_for


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
        parameters=[RECORD_ID],
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
                e429=CHECKS_OVER_BUDGET,
                e409="`integrity_check_failed`: the stored data differs from the chain; "
                "`not_anchored_yet`: try again shortly; `identity_check_failed`: the owner's "
                "key commitment on chain differs from the key the portal holds",
            ),
        },
    )
    def get(self, request: Request, record_id: str) -> Response:
        viewer = caller_owner(request)
        credential, token = caller_credential(request)
        opened = record_open(
            record_id=record_uuid(record_id), viewer=viewer, credential=credential, token=token
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
