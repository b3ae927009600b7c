"""How many registrations the open sign-up page takes, per client address and overall.

Each registration makes the operator fund and enroll an EOA on chain, so sign-ups are limited
by SIGNUP_RATE_PER_ADDRESS and SIGNUP_RATE_TOTAL ("5/hour"): sliding windows kept in Redis,
checked and counted by one script, so they hold across every web process and two requests
cannot both take the last place. What counts is a registration that would create an owner (a
POST whose form is valid); one the service then refuses (a taken username, a weak key) is
given back, and invalid forms never count. A Redis that is down lets sign-ups through (and
logs it), as the API's rate limits do: the funding budget still bounds what they cost.
"""

import logging
import math
import time
import uuid
from dataclasses import dataclass

from django.conf import settings
from redis.exceptions import RedisError

from core.rates import rate_parse
from core.redis_client import get_redis, redis_key

logger = logging.getLogger(__name__)

# KEYS: one sliding window each (a sorted set of attempts scored by time). ARGV: now, the
# attempt's member, then the limit and the window (seconds) of each key. Returns "0" when the
# attempt was counted in every window, else the seconds until one may be tried again.
_TAKE = """
local now = tonumber(ARGV[1])
local wait = 0
for i, key in ipairs(KEYS) do
  local limit = tonumber(ARGV[1 + 2 * i])
  local window = tonumber(ARGV[2 + 2 * i])
  redis.call('ZREMRANGEBYSCORE', key, '-inf', now - window)
  local count = redis.call('ZCARD', key)
  if count >= limit then
    local w = window
    if limit > 0 then
      local frees = redis.call('ZRANGE', key, count - limit, count - limit, 'WITHSCORES')
      w = tonumber(frees[2]) + window - now
    end
    if w > wait then wait = w end
  end
end
if wait > 0 then return tostring(wait) end
for i, key in ipairs(KEYS) do
  redis.call('ZADD', key, now, ARGV[2])
  redis.call('PEXPIRE', key, math.ceil(tonumber(ARGV[2 + 2 * i]) * 1000))
end
return '0'
"""


@dataclass(frozen=True)
class SignupSlot:
    """One registration's place in the sign-up limits, or why there is none."""

    allowed: bool
    # Seconds until a registration from this address may be tried again (when not allowed).
    retry_after: int = 0
    keys: tuple[str, ...] = ()
    member: str = ""


def signup_slot_take(*, address: str | None) -> SignupSlot:
    """Count a registration from `address` if both limits allow it."""
    # One hash tag for both windows: the script touches the two, so in a Redis Cluster they
    # must share a slot.
    windows = [
        (redis_key("{signup}", "address", address or "unknown"), settings.SIGNUP_RATE_PER_ADDRESS),
        (redis_key("{signup}", "total"), settings.SIGNUP_RATE_TOTAL),
    ]
    keys = tuple(key for key, _ in windows)
    now = time.time()
    member = f"{now:.6f}:{uuid.uuid4().hex}"
    args: list[object] = [now, member]
    for _, rate in windows:
        args.extend(rate_parse(rate))
    try:
        wait = float(get_redis().register_script(_TAKE)(keys=list(keys), args=args))
    except (RedisError, OSError) as exc:
        logger.warning("sign-up limits not checked, Redis is unavailable: %s", exc)
        return SignupSlot(allowed=True)
    if wait > 0:
        return SignupSlot(allowed=False, retry_after=max(1, math.ceil(wait)))
    return SignupSlot(allowed=True, keys=keys, member=member)


def signup_slot_give_back(slot: SignupSlot) -> None:
    """Uncount a registration that created nothing."""
    if not slot.keys:
        return
    try:
        pipe = get_redis().pipeline()
        for key in slot.keys:
            pipe.zrem(key, slot.member)
        pipe.execute()
    except (RedisError, OSError) as exc:
        logger.warning("a refused sign-up still counts, Redis is unavailable: %s", exc)
