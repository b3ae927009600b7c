"""Who calls the REST API and how often: robot and owner API tokens, what each may do, the
caller's owner, rate limits.

Both kinds of token come as `Authorization: Token <key>` and are compared by SHA-256. A robot
token is a device credential (a stolen robot must not give away its owner's data): it uploads
and reads the status of that robot's own uploads, nothing else. Reading content, listing what
others shared, granting and revoking need the owner: a browser session, or an owner API token
(`aro_...`) with the scope for it (`OwnerCredential`). Rate limits are counted in the shared
cache (Redis), so they hold across every web process; a cache that is down lets requests
through rather than failing them.
"""

import logging
from typing import TYPE_CHECKING, Any

from django.urls import reverse
from django.utils import timezone
from drf_spectacular.extensions import OpenApiAuthenticationExtension
from redis.exceptions import RedisError
from rest_framework import authentication, exceptions, throttling
from rest_framework.permissions import BasePermission
from rest_framework.request import Request
from rest_framework.settings import api_settings

from accounts.errors import InsufficientScope
from accounts.models import Owner, OwnerToken, Robot
from accounts.selectors import (
    OWNER_TOKEN_PREFIX,
    owner_for_user,
    owner_token_by_key,
    robot_by_token,
)
from accounts.services.api_tokens import owner_token_mark_used
from core.logging import log_context_add
from core.redis_client import get_redis, redis_key

if TYPE_CHECKING:  # rest_framework.views imports this module through the settings
    from rest_framework.views import APIView

logger = logging.getLogger(__name__)

AUTH_KEYWORD = "Token"


def _token_key(request: Request) -> str | None:
    """The key of an `Authorization: Token <key>` header; None without such a header."""
    header = authentication.get_authorization_header(request).split()
    if not header or header[0].lower() != AUTH_KEYWORD.lower().encode():
        return None
    if len(header) != 2:
        raise exceptions.AuthenticationFailed("use the header `Authorization: Token <key>`")
    try:
        return header[1].decode("ascii")
    except UnicodeDecodeError:
        raise exceptions.AuthenticationFailed("the token has characters it cannot have") from None


class OwnerTokenAuthentication(authentication.BaseAuthentication):
    """Authenticates an owner API token; `request.user` is its owner's user, `request.auth` the
    OwnerToken. Keys that are no owner token are left to RobotTokenAuthentication (next)."""

    keyword = AUTH_KEYWORD

    def authenticate(self, request: Request) -> tuple[Any, OwnerToken] | None:
        key = _token_key(request)
        if key is None or not key.startswith(OWNER_TOKEN_PREFIX):
            return None
        token = owner_token_by_key(key)
        if token is None:
            return None  # a robot token may start the same way, however unlikely
        if token.revoked_at is not None:
            raise exceptions.AuthenticationFailed("this API token was revoked")
        if token.expires_at <= timezone.now():
            raise exceptions.AuthenticationFailed(
                f"this API token expired at {token.expires_at:%Y-%m-%d %H:%M} UTC: "
                f"make a new one at {reverse('api-tokens')}"
            )
        if not token.owner.user.is_active:
            raise exceptions.AuthenticationFailed("the token's owner account is disabled")
        owner_token_mark_used(token=token)
        log_context_add(owner=token.owner_id)
        return token.owner.user, token

    def authenticate_header(self, request: Request) -> str:
        return self.keyword


class RobotTokenAuthentication(authentication.BaseAuthentication):
    """Authenticates a robot; `request.user` is its owner's user, `request.auth` the Robot."""

    keyword = AUTH_KEYWORD

    def authenticate(self, request: Request) -> tuple[Any, Robot] | None:
        key = _token_key(request)
        if key is None:
            return None
        robot = robot_by_token(key)
        if robot is None:
            raise exceptions.AuthenticationFailed("unknown or revoked token")
        if not robot.owner.user.is_active:
            raise exceptions.AuthenticationFailed("the robot's owner account is disabled")
        log_context_add(owner=robot.owner_id, robot=str(robot.pk))
        return robot.owner.user, robot

    def authenticate_header(self, request: Request) -> str:
        return self.keyword


class OwnerTokenScheme(OpenApiAuthenticationExtension):
    """How the OpenAPI schema describes owner API tokens."""

    target_class = OwnerTokenAuthentication
    name = "ownerToken"

    def get_security_definition(self, auto_schema: Any) -> dict[str, str]:
        return {
            "type": "apiKey",
            "in": "header",
            "name": "Authorization",
            "description": (
                "`Token aro_<key>`, an owner API token made at `/account/tokens/`: scoped "
                "(`read`: records and their content; `share`: grants), expiring, revocable"
            ),
        }


class RobotTokenScheme(OpenApiAuthenticationExtension):
    """How the OpenAPI schema describes robot tokens."""

    target_class = RobotTokenAuthentication
    name = "robotToken"

    def get_security_definition(self, auto_schema: Any) -> dict[str, str]:
        return {
            "type": "apiKey",
            "in": "header",
            "name": "Authorization",
            "description": (
                "`Token <key>`, the robot's token printed by `manage.py robot_create`: uploads, "
                "and the status of that robot's own uploads, nothing else"
            ),
        }


def caller_robot(request: Request) -> Robot | None:
    """The robot behind a robot-token request, else None."""
    return request.auth if isinstance(request.auth, Robot) else None


def caller_owner_token(request: Request) -> OwnerToken | None:
    """The owner API token behind a request, else None."""
    return request.auth if isinstance(request.auth, OwnerToken) else None


def caller_owner(request: Request) -> Owner:
    """The owner a request acts for: an owner token's, or the signed-in user's. A robot token
    never acts for its owner."""
    if caller_robot(request) is not None:
        raise exceptions.PermissionDenied("a robot token cannot act for its owner")
    token = caller_owner_token(request)
    if token is not None:
        return token.owner
    owner = owner_for_user(request.user)
    if owner is None:
        raise exceptions.PermissionDenied("this account is not a robot owner")
    return owner


class OwnerCredential(BasePermission):
    """The caller acts as the owner: a browser session, or an owner API token with `scope`.

    A robot token is refused (403 `permission_denied`), unless `robots` is set: the view then
    answers only about that robot's own uploads. A token without the scope is refused with 403
    `insufficient_scope`. `action` completes "cannot ..." in the refusal.
    """

    def __init__(self, scope: str, action: str, *, robots: bool = False) -> None:
        self.scope, self.action, self.robots = scope, action, robots

    def has_permission(self, request: Request, view: "APIView") -> bool:
        if caller_robot(request) is not None:
            if self.robots:
                return True
            raise exceptions.PermissionDenied(
                f"a robot token cannot {self.action}: it only uploads and reads the status of "
                "its own uploads. Sign in to the portal, or use an owner API token with the "
                f"`{self.scope}` scope (made at {reverse('api-tokens')})"
            )
        token = caller_owner_token(request)
        if token is not None and self.scope not in token.scopes:
            raise InsufficientScope(
                f"this API token cannot {self.action}: that needs the `{self.scope}` scope, "
                f"and it has {', '.join(token.scopes) or 'none'}"
            )
        return True


# --- rate limits ------------------------------------------------------------------------------


class _SharedRateThrottle(throttling.SimpleRateThrottle):
    """Rates read from the settings at each request, counted in the portal's Redis namespace
    by a sliding window: the count of this window plus the last window's, weighted by how much
    of it still overlaps the last `duration` seconds. One round trip and two small integers per
    request, where DRF's history (a list of every request's time, pickled into the cache and
    read back whole) grows with the rate: thousands of entries at API_RATE_USER."""

    def get_rate(self) -> str | None:
        return api_settings.DEFAULT_THROTTLE_RATES.get(self.scope)

    def allow_request(self, request: Request, view: "APIView") -> bool:
        if self.rate is None:
            return True
        self.key = self.get_cache_key(request, view)
        if self.key is None:
            return True
        counts = _window_counts(request, view, now=self.timer())
        if self.key not in counts.counted:
            counts.count([self])  # a throttle the view does not list: counted on its own
        if counts.failed:
            return True
        counted, before = counts.counted[self.key]
        into = counts.now % self.duration
        overlap = (self.duration - into) / self.duration
        if before * overlap + counted <= self.num_requests:
            return True
        self.retry_after = max(1.0, self.duration - into)
        return False

    def window_keys(self, now: float) -> tuple[str, str]:
        """This window's counter and the last window's."""
        window = int(now // self.duration)
        return f"{self.key}:{window}", f"{self.key}:{window - 1}"

    def wait(self) -> float | None:
        return getattr(self, "retry_after", None)

    def cache_key_for(self, ident: object) -> str:
        return redis_key("throttle", self.scope, ident)


class _WindowCounts:
    """The sliding-window counts of one request for every rate limit of its view, counted in
    one round trip to Redis (a robot's upload has two: its owner's and its own)."""

    def __init__(self, now: float) -> None:
        self.now = now
        self.counted: dict[str, tuple[int, int]] = {}  # key: (this window, last window)
        self.failed = False

    def count(self, throttles: list[_SharedRateThrottle]) -> None:
        throttles = [throttle for throttle in throttles if throttle.key not in self.counted]
        if not throttles or self.failed:
            return
        try:
            with get_redis().pipeline(transaction=False) as pipe:
                for throttle in throttles:
                    current, previous = throttle.window_keys(self.now)
                    pipe.incr(current)
                    pipe.expire(current, int(throttle.duration) * 2 + 1)
                    pipe.get(previous)
                answers = pipe.execute()
        except (RedisError, OSError) as exc:
            logger.warning("rate limit not checked, Redis is unavailable: %s", exc)
            self.failed = True
            return
        for number, throttle in enumerate(throttles):
            counted, _, before = answers[3 * number : 3 * number + 3]
            self.counted[throttle.key] = (int(counted), int(before or 0))


def _window_counts(request: Request, view: "APIView | None", *, now: float) -> _WindowCounts:
    """The request's counts, made on its first rate limit for all of the view's at once, at
    that limit's `now`."""
    counts = getattr(request, "_authros_window_counts", None)
    if counts is None:
        counts = _WindowCounts(now)
        throttles = []
        for throttle in view.get_throttles() if view is not None else ():
            if isinstance(throttle, _SharedRateThrottle) and throttle.rate is not None:
                throttle.key = throttle.get_cache_key(request, view)
                if throttle.key is not None:
                    throttles.append(throttle)
        counts.count(throttles)
        request._authros_window_counts = counts
    return counts


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


class PairingRateThrottle(_SharedRateThrottle):
    """Pairing requests and their polls, per client address (`API_RATE_PAIRING`): robots
    that are not paired yet have no credentials to be counted by."""

    scope = "pairing"

    def get_cache_key(self, request: Request, view: "APIView") -> str | None:
        return self.cache_key_for(self.get_ident(request))
