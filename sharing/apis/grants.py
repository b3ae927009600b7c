"""`/api/v1/grants/` and `/api/v1/grants/{grantee}/`: grants given and received, granting
(with optional terms), changing a grant's terms, and revoking."""

from typing import Any, ClassVar

from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import serializers, status
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner, caller_owner_token
from core.api_errors import error_responses
from sharing.apis.fields import (
    MAX_OWNER_IDENTIFIER,
    OWNER_ONLY,
    ROBOT_REFUSED,
    SHARE,
    NullIfBlankCharField,
    RecordSelectionSerializer,
    TextField,
)
from sharing.grant_terms import GrantTerms, grant_terms_make
from sharing.models import Grant
from sharing.selectors.grants import (
    grant_list_given,
    grant_list_received,
    grantee_resolve,
    owner_resolve,
)
from sharing.services.grants import GRANT_MADE_WITH, grant_create, grant_revoke, grant_terms_change


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


class GrantTermsInputSerializer(RecordSelectionSerializer):
    """The optional terms of a grant: leave them all out for all records, without expiry."""

    class Meta:
        ref_name = "GrantTerms"

    selection_help: ClassVar[dict[str, str]] = {
        "robots": "only these robots' records (ids of your robots); default: all robots",
        "topics": "only these topics' records; default: all topics",
        "since": "only records captured at or after (ISO 8601)",
        "until": "only records captured before (ISO 8601)",
    }
    window_nullable: ClassVar[bool] = True

    expires_at = serializers.DateTimeField(
        required=False,
        allow_null=True,
        help_text="the grant gives no access from then on (ISO 8601, at least 5 minutes "
        "ahead, whole seconds); default: never",
    )

    def terms_for(self, owner: Any) -> GrantTerms:
        return grant_terms_make(
            owner=owner, **self.selection(), expires_at=self.validated_data.get("expires_at")
        )


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
                "`grantee_not_registered`, `owner_ambiguous` (another owner's username looks "
                "like the one given: give the grantee's 0x address)",
            ),
        },
    )
    def post(self, request: Request) -> Response:
        owner = caller_owner(request)
        payload = self.InputSerializer(data=request.data)
        payload.is_valid(raise_exception=True)
        terms = payload.terms_for(owner)
        grantee = grantee_resolve(payload.validated_data["grantee"])
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
