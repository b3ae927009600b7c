"""What every owner page wraps itself in: the owner check, the page rate limit and the no-cache
answer.

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


# The settings holding each page scope's rate, "<requests>/<second|minute|hour|day>".
PAGE_RATE_SETTINGS = {"page": "PAGE_RATE_USER", "content": "PAGE_RATE_CONTENT"}


def page_throttle(scope: str = "page", *, cost: int = 1) -> Callable[[OwnerView], OwnerView]:
    """Limit how often one signed-in user loads pages: over the limit, a 429 page with
    Retry-After.

    Every page counts 1 against PAGE_RATE_USER. A page in the "content" scope (one that runs
    an integrity check: a record, its download, a gallery page) also counts `cost` against
    PAGE_RATE_CONTENT: what it costs the worker, in single record checks (a gallery page
    checks its images in one batched run, so it passes less than one per image).

    Counted per user in fixed windows in Redis, shared by every web process; when Redis is
    down the page is served uncounted, as the API's throttles do. Put it under
    `owner_required`, so that anonymous requests go to the sign-in page uncounted.
    """
    if scope not in PAGE_RATE_SETTINGS:
        raise ValueError(f"unknown page throttle scope {scope!r}")

    def decorate(view: OwnerView) -> OwnerView:
        @wraps(view)
        def wrapped(request: HttpRequest, *args: object, **kwargs: object) -> HttpResponse:
            if request.user.is_authenticated:
                charges = [("page", 1)] if scope == "page" else [("page", 1), (scope, cost)]
                for charged, amount in charges:
                    wait = page_rate_charge(scope=charged, user_id=request.user.pk, cost=amount)
                    if wait is not None:
                        return _too_many_requests(request, wait)
            return view(request, *args, **kwargs)

        return wrapped

    return decorate


def page_rate_charge(*, scope: str, user_id: int, cost: int = 1) -> int | None:
    """Count `cost` against the user's rate in `scope`; None if within it, else the seconds
    until the current window ends (the Retry-After). None too when Redis cannot count."""
    rate = getattr(settings, PAGE_RATE_SETTINGS[scope], "")
    if not rate:
        return None
    limit, period = rate_parse(rate)
    now = time.time()
    window = int(now // period)
    key = redis_key("page-throttle", scope, user_id, window)
    try:
        pipe = get_redis().pipeline()
        pipe.set(key, 0, ex=period + 1, nx=True)
        pipe.incrby(key, cost)
        _created, used = pipe.execute()
    except (RedisError, OSError) as exc:
        logger.warning("page rate limit not checked, Redis is unavailable: %s", exc)
        return None
    if used <= limit:
        return None
    return max(1, math.ceil((window + 1) * period - now))


def _too_many_requests(request: HttpRequest, wait: int) -> HttpResponse:
    response = render(request, "429.html", {"retry_after": wait}, status=429)
    response["Retry-After"] = str(wait)
    return no_store(response)
