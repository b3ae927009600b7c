"""What every owner page wraps itself in: the owner check, the page rate limit (and the 429
page of a page's work over its budget) and the no-cache answer.

Kept apart from the views so that the pages of every app (and the project's own) use them
without importing one another's views.
"""

import logging
import math
import time
from collections.abc import Callable
from functools import wraps

from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from redis.exceptions import RedisError

from accounts.selectors import owner_for_user
from core.errors import DomainError
from core.rates import rate_parse
from core.redis_client import get_redis, redis_key

logger = logging.getLogger(__name__)

OwnerView = Callable[..., HttpResponse]


def owner_required(view: OwnerView) -> OwnerView:
    """Login required, and the user must be an owner: sets `request.owner`.

    Operator accounts (admin users without an owner) get a page pointing to the admin.
    """

    @wraps(view)
    @login_required
    def wrapped(request: HttpRequest, *args: object, **kwargs: object) -> HttpResponse:
        owner = owner_for_user(request.user)
        if owner is None:
            return render(request, "accounts/not_an_owner.html", status=403)
        request.owner = owner
        return view(request, *args, **kwargs)

    return wrapped


def no_store(response: HttpResponse) -> HttpResponse:
    """Keep a page that shows a secret or decrypted data out of every cache."""
    response["Cache-Control"] = "no-store, private"
    response["Pragma"] = "no-cache"
    return response


def page_throttle() -> Callable[[OwnerView], OwnerView]:
    """Limit how often one signed-in user loads pages: over the limit, a 429 page with
    Retry-After.

    Every page counts 1 against PAGE_RATE_USER, per user in fixed windows in Redis, shared by
    every web process; when Redis is down the page is served uncounted, as the API's throttles
    do. A page whose work is refused for now with a 429 (its integrity checks over the
    caller's CHECK_BUDGET) gets the same 429 page, with the reason and its Retry-After. Put it
    under `owner_required`, so that anonymous requests go to the sign-in page uncounted.
    """

    def decorate(view: OwnerView) -> OwnerView:
        @wraps(view)
        def wrapped(request: HttpRequest, *args: object, **kwargs: object) -> HttpResponse:
            if request.user.is_authenticated:
                wait = page_rate_charge(user_id=request.user.pk)
                if wait is not None:
                    return _too_many_requests(request, wait)
            try:
                return view(request, *args, **kwargs)
            except DomainError as exc:
                if exc.http_status != 429:
                    raise
                return _too_many_requests(request, exc.retry_after or 60, reason=str(exc))

        return wrapped

    return decorate


def page_rate_charge(*, user_id: int) -> int | None:
    """Count a page against the user's PAGE_RATE_USER; None if within it, else the seconds
    until the current window ends (the Retry-After). None too when Redis cannot count."""
    rate = settings.PAGE_RATE_USER
    if not rate:
        return None
    limit, period = rate_parse(rate)
    now = time.time()
    window = int(now // period)
    key = redis_key("page-throttle", "page", user_id, window)
    try:
        pipe = get_redis().pipeline()
        pipe.set(key, 0, ex=period + 1, nx=True)
        pipe.incr(key)
        _created, used = pipe.execute()
    except (RedisError, OSError) as exc:
        logger.warning("page rate limit not checked, Redis is unavailable: %s", exc)
        return None
    if used <= limit:
        return None
    return max(1, math.ceil((window + 1) * period - now))


def _too_many_requests(request: HttpRequest, wait: int, *, reason: str = "") -> HttpResponse:
    context = {"retry_after": wait, "reason": reason}
    response = render(request, "429.html", context, status=429)
    response["Retry-After"] = str(wait)
    return no_store(response)
