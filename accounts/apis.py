"""REST API v1 of accounts: the portal's SM2 public key for the key exchange."""

from drf_spectacular.utils import extend_schema
from rest_framework import serializers
from rest_framework.permissions import AllowAny
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.keyexchange import portal_sm2_public_key
from core.api_errors import error_responses

SM2_CIPHERTEXT_MODE = "C1C3C2"


class Sm2PublicKeyApi(APIView):
    """`GET /api/v1/sm2-public-key/`: what to encrypt an SM4 key to before sending it."""

    authentication_classes = ()
    permission_classes = (AllowAny,)

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "Sm2PublicKey"

        public_key = serializers.RegexField(
            r"^04[0-9a-f]{128}$", help_text="SM2 (sm2p256v1) public key, `04||x||y` as hex"
        )
        mode = serializers.ChoiceField(
            choices=[SM2_CIPHERTEXT_MODE],
            help_text="ciphertext layout the portal expects (gmssl mode=1, sm-crypto mode 1)",
        )

    @extend_schema(
        operation_id="sm2_public_key",
        summary="The portal's SM2 public key",
        auth=[],
        responses={200: OutputSerializer, **error_responses()},
    )
    def get(self, request: Request) -> Response:
        data = {"public_key": portal_sm2_public_key(), "mode": SM2_CIPHERTEXT_MODE}
        return Response(self.OutputSerializer(data).data)
