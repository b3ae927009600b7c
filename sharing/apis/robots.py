"""`/api/v1/robots/{id}/status/`: is a robot alive, and what it sends (the robot page polls
it). Reads no content: nothing is checked against the chain."""

from django.utils import timezone
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, extend_schema
from rest_framework import serializers
from rest_framework.permissions import BasePermission, IsAuthenticated
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from accounts.authentication import OwnerCredential, caller_owner
from accounts.lastseen import seen_ago_text
from core.api_errors import error_responses
from sharing.apis.fields import OWNER_ONLY, READ, ROBOT_REFUSED
from sharing.errors import RobotNotFound
from sharing.robot_status import RobotActivity, robot_activity, robot_of_owner


class RobotTopicRateSerializer(serializers.Serializer):
    class Meta:
        ref_name = "RobotTopicRate"

    topic = serializers.CharField()
    type = serializers.CharField(source="data_type", help_text="ROS message type")
    last_minute = serializers.IntegerField(help_text="messages captured in the last minute")
    last_hour = serializers.IntegerField(help_text="messages captured in the last hour")
    per_second_minute = serializers.FloatField(help_text="messages per second, last minute")
    per_second_hour = serializers.FloatField(
        help_text="messages per second, last hour (over hour_seconds)"
    )
    hour_seconds = serializers.FloatField(
        help_text="what the hour's rate is over: 3600, or less for a robot added within the hour"
    )


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
