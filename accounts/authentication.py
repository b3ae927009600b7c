"""Who calls the REST API and how often: robot tokens, the caller's owner, rate limits.

Robot tokens: `Authorization: Token <key>`, compared by SHA-256. Rate limits are counted in
the shared cache (Redis), so they hold across every web process; a cache that is down lets
requests through rather than failing them.
"""

import logging
from typing import TYPE_CHECKING, Any

from django.conf import settings
from drf_spectacular.extensions import OpenApiAuthenticationExtension
from redis.exceptions import RedisError
from rest_framework import authentication, exceptions, throttling
from rest_framework.request import Request
from rest_framework.settings import api_settings

from accounts.models import Owner, Robot
from accounts.selectors import owner_for_user, robot_by_token

if TYPE_CHECKING:  # rest_framework.views imports this module through the settings
    from rest_framework.views import APIView

logger = logging.getLogger(__name__)


class RobotTokenAuthentication(authentication.BaseAuthentication):
    """Authenticates a robot; `request.user` is its owner's user, `request.auth` the Robot."""

    keyword = "Token"

    def authenticate(self, request: Request) -> tuple[Any, Robot] | None:
        header = authentication.get_authorization_header(request).split()
        if not header or header[0].lower() != self.keyword.lower().encode():
            return None
        if len(header) != 2:
            raise exceptions.AuthenticationFailed("use the header `Authorization: Token <key>`")
        try:
            token = header[1].decode("ascii")
        except UnicodeDecodeError:
            raise exceptions.AuthenticationFailed(
                "the token has characters it cannot have"
            ) from None
        robot = robot_by_token(token)
        if robot is None:
            raise exceptions.AuthenticationFailed("unknown or revoked robot token")
        if not robot.owner.user.is_active:
            raise exceptions.AuthenticationFailed("the robot's owner account is disabled")
        return robot.owner.user, robot

    def authenticate_header(self, request: Request) -> str:
        return self.keyword


class RobotTokenScheme(OpenApiAuthenticationExtension):
    """How the OpenAPI schema describes robot tokens."""

    target_class = RobotTokenAuthentication
    name = "robotToken"

    def get_security_definition(self, auto_schema: Any) -> dict[str, str]:
        return {
            "type": "apiKey",
            "in": "header",
            "name": "Authorization",
            "description": "`Token <key>`, the robot's token printed by `manage.py robot_create`",
        }


def caller_robot(request: Request) -> Robot | None:
    """The robot behind a token-authenticated request, else None (a browser session)."""
    return request.auth if isinstance(request.auth, Robot) else None


def caller_owner(request: Request) -> Owner:
    """The owner a request acts for: the robot's owner, or the logged-in user's owner."""
    robot = caller_robot(request)
    if robot is not None:
        return robot.owner
    owner = owner_for_user(request.user)
    if owner is None:
        raise exceptions.PermissionDenied("this account is not a robot owner")
    return owner


# --- rate limits ------------------------------------------------------------------------------


class _SharedRateThrottle(throttling.SimpleRateThrottle):
    """Rates read from the settings at each request; history kept in the portal's namespace."""

    def get_rate(self) -> str | None:
        return api_settings.DEFAULT_THROTTLE_RATES.get(self.scope)

    def allow_request(self, request: Request, view: "APIView") -> bool:
        try:
            return super().allow_request(request, view)
        except (RedisError, OSError) as exc:
            logger.warning("rate limit not checked, the cache is unavailable: %s", exc)
            return True

    def cache_key_for(self, ident: object) -> str:
        return f"{settings.REDIS_KEY_PREFIX}:throttle:{self.scope}:{ident}"


class AnonRateThrottle(_SharedRateThrottle):
    """Requests without credentials, per client address (`API_RATE_ANON`)."""

    scope = "anon"

    def get_cache_key(self, request: Request, view: "APIView") -> str | None:
        if request.user and request.user.is_authenticated:
            return None
        return self.cache_key_for(self.get_ident(request))


class OwnerRateThrottle(_SharedRateThrottle):
    """Requests of one owner, from its browser sessions and all its robots (`API_RATE_USER`)."""

    scope = "user"

    def get_cache_key(self, request: Request, view: "APIView") -> str | None:
        if not (request.user and request.user.is_authenticated):
            return None
        return self.cache_key_for(request.user.pk)


class RobotUploadRateThrottle(_SharedRateThrottle):
    """Uploads of one robot (`API_RATE_UPLOAD`)."""

    scope = "upload"

    def get_cache_key(self, request: Request, view: "APIView") -> str | None:
        robot = caller_robot(request)
        if robot is None or request.method != "POST":
            return None
        return self.cache_key_for(robot.pk)
