"""REST API v1 of accounts: the portal's SM2 public key for the key exchange, and robot
pairing (a robot's SM2 key pair, its owner's approval, the owner's key sent to it encrypted)."""

import uuid

from django.core.validators import ProhibitNullCharactersValidator, RegexValidator
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, extend_schema
from rest_framework import exceptions, serializers, status
from rest_framework.permissions import AllowAny, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import PairingRateThrottle, caller_robot
from accounts.errors import PairingNotFound
from accounts.keyexchange import portal_sm2_public_key
from accounts.models import RobotPairing
from accounts.selectors import (
    KEY_ID_HEADER,
    pairing_code_display,
    public_key_fingerprint,
    robot_key_for,
)
from accounts.services.pairing import robot_pairing_collect, robot_pairing_request
from core.api_errors import error_responses

SM2_CIPHERTEXT_MODE = "C1C3C2"
# Seconds a robot waits between two asks for its pairing answer.
PAIRING_POLL_INTERVAL = 3


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


class _Text(serializers.CharField):
    """A string and only a string (DRF's CharField takes 5 for "5"), without NUL characters,
    which the schema says too (as sharing.apis.fields.TextField, which this layer cannot import)."""

    def __init__(self, **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.validators = [
            validator
            for validator in self.validators
            if not isinstance(validator, ProhibitNullCharactersValidator)
        ]
        self.validators.append(
            RegexValidator(r"^[^\x00]*$", message="NUL characters are not allowed")
        )

    def to_internal_value(self, data: object) -> str:
        if not isinstance(data, str):
            self.fail("invalid")
        return super().to_internal_value(data)


class RobotPairingsApi(APIView):
    """`POST /api/v1/robot-pairings/`: a robot asks to be paired (`python -m ros_agent pair`)."""

    authentication_classes = ()
    permission_classes = (AllowAny,)
    throttle_classes = (PairingRateThrottle,)

    class InputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotPairingRequest"

        name = _Text(max_length=100, help_text="the robot's name, as its owner will see it")
        public_key = serializers.RegexField(
            r"^(04)?[0-9a-fA-F]{128}$",
            help_text="the robot's SM2 (sm2p256v1) public key, `04||x||y` as hex; its private "
            "key never leaves the robot; a point off the curve is refused",
        )

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotPairingCreated"

        id = serializers.UUIDField(help_text="the request; the robot polls .../{id}/collect/")
        code = serializers.CharField(
            help_text="short code the robot shows its owner, who types it on the robots page: "
            "for people to match, not a credential"
        )
        secret = serializers.CharField(
            help_text="shown once, kept by the robot: only it collects the answer with it"
        )
        fingerprint = serializers.CharField(help_text="of the public key, for people to compare")
        expires_at = serializers.DateTimeField()
        poll_interval = serializers.IntegerField(help_text="seconds between two polls")

    @extend_schema(
        operation_id="robot_pairing_create",
        summary="A robot asks to be paired",
        auth=[],
        request=InputSerializer,
        responses={
            201: OutputSerializer,
            **error_responses(
                400, e400="`invalid_pairing_request`: a bad name, or a public key off the curve"
            ),
        },
    )
    def post(self, request: Request) -> Response:
        given = self.InputSerializer(data=request.data)
        given.is_valid(raise_exception=True)
        pairing, secret = robot_pairing_request(**given.validated_data)
        data = {
            "id": pairing.pk,
            "code": pairing_code_display(pairing.code),
            "secret": secret,
            "fingerprint": public_key_fingerprint(pairing.public_key),
            "expires_at": pairing.expires_at,
            "poll_interval": PAIRING_POLL_INTERVAL,
        }
        response = Response(self.OutputSerializer(data).data, status=status.HTTP_201_CREATED)
        response["Cache-Control"] = "no-store"
        return response


class RobotPairingCollectApi(APIView):
    """`POST /api/v1/robot-pairings/{id}/collect/`: the robot, with its secret, asks for its
    answer: 202 while pending, then once 200 with its token and its owner's key."""

    authentication_classes = ()
    permission_classes = (AllowAny,)
    throttle_classes = (PairingRateThrottle,)

    class InputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotPairingCollect"

        secret = _Text(max_length=100, help_text="what the request's 201 answer gave")

    class PendingSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotPairingPending"

        state = serializers.ChoiceField(choices=["pending"])
        expires_at = serializers.DateTimeField()
        poll_interval = serializers.IntegerField()

    class DeliveredSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotPairingDelivered"

        state = serializers.ChoiceField(choices=["approved"])
        robot = serializers.UUIDField(help_text="the robot's id, for its envelopes' header")
        name = serializers.CharField()
        owner = serializers.CharField(help_text="the owner's username, for the header")
        topics = serializers.ListField(child=serializers.DictField(), help_text="to record")
        token_sm2 = serializers.CharField(
            help_text="the robot's upload token, SM2-encrypted to its public key (C1C3C2 hex)"
        )
        key_id = serializers.CharField(help_text="the owner's current SM4 key's id, hex")
        key_sm2 = serializers.CharField(
            help_text="the owner's current SM4 key, SM2-encrypted to the robot (C1C3C2 hex)"
        )
        mode = serializers.ChoiceField(choices=[SM2_CIPHERTEXT_MODE])

    @extend_schema(
        operation_id="robot_pairing_collect",
        parameters=[
            OpenApiParameter(
                "pairing_id", OpenApiTypes.UUID, OpenApiParameter.PATH, description="the request"
            )
        ],
        summary="A robot collects its pairing answer (once)",
        auth=[],
        request=InputSerializer,
        responses={
            200: DeliveredSerializer,
            202: PendingSerializer,
            **error_responses(
                400,
                403,
                404,
                409,
                e403="`pairing_secret_mismatch`: not the robot's secret; `pairing_refused`",
                e404="`pairing_not_found`",
                e409="`pairing_expired`, or `pairing_already_collected`: handed out once",
            ),
        },
    )
    def post(self, request: Request, pairing_id: str) -> Response:
        given = self.InputSerializer(data=request.data)
        given.is_valid(raise_exception=True)
        try:
            request_id = uuid.UUID(pairing_id)
        except ValueError:
            raise PairingNotFound("no pairing request has this id") from None
        answer = robot_pairing_collect(pairing_id=request_id, secret=given.validated_data["secret"])
        pairing = answer.pairing
        if pairing.state == RobotPairing.State.PENDING:
            data = {
                "state": "pending",
                "expires_at": pairing.expires_at,
                "poll_interval": PAIRING_POLL_INTERVAL,
            }
            response = Response(self.PendingSerializer(data).data, status=status.HTTP_202_ACCEPTED)
        else:
            robot = pairing.robot
            data = {
                "state": "approved",
                "robot": robot.pk,
                "name": robot.name,
                "owner": pairing.owner.username,
                "topics": robot.topics,
                "token_sm2": answer.token_sm2,
                "key_id": answer.key_id,
                "key_sm2": answer.key_sm2,
                "mode": SM2_CIPHERTEXT_MODE,
            }
            response = Response(self.DeliveredSerializer(data).data)
        response["Cache-Control"] = "no-store"
        return response


class RobotKeyApi(APIView):
    """`GET /api/v1/robot-key/`: a paired robot fetches its owner's current SM4 key, encrypted
    to its own SM2 public key; an unpaired or revoked robot gets nothing."""

    permission_classes = (IsAuthenticated,)

    class OutputSerializer(serializers.Serializer):
        class Meta:
            ref_name = "RobotKey"

        key_id = serializers.CharField(help_text="the owner's current SM4 key's id, hex")
        key_sm2 = serializers.CharField(
            help_text="that key, SM2-encrypted to the robot's paired public key (C1C3C2 hex)"
        )
        mode = serializers.ChoiceField(choices=[SM2_CIPHERTEXT_MODE])
        created_at = serializers.DateTimeField(help_text="when the key became current")

    @extend_schema(
        operation_id="robot_key",
        summary="The owner's current key, for a paired robot",
        auth=[{"robotToken": []}],
        responses={
            200: OutputSerializer,
            **error_responses(
                401,
                403,
                409,
                e401="`not_authenticated`: no robot token, or a revoked one (an unpaired robot)",
                e403="`permission_denied`: not a robot token",
                e409="`robot_not_paired`: a robot added by hand has no SM2 key to send it to",
            ),
        },
    )
    def get(self, request: Request) -> Response:
        robot = caller_robot(request)
        if robot is None:
            raise exceptions.PermissionDenied("only a paired robot's token fetches the key")
        key, key_sm2 = robot_key_for(robot)
        data = {
            "key_id": key.key_id,
            "key_sm2": key_sm2,
            "mode": SM2_CIPHERTEXT_MODE,
            "created_at": key.created_at,
        }
        response = Response(self.OutputSerializer(data).data)
        response["Cache-Control"] = "no-store"
        response[KEY_ID_HEADER] = key.key_id
        return response
