"""The budget of integrity checks: how many records one caller may have the workers check, per
CHECK_BUDGET ("<records>/<period>"), whatever asks (a record page, its download, a gallery, the
robot page, the content API, a series); and the cancelling of a read's queued checks once its
request stops waiting.

The caller is the viewer the read is for: an owner or a grantee, an owner API token's calls
being its owner's (so a stolen token spends its owner's budget, no more). Each caller has a
bucket in Redis (one key, changed by one Lua script timed by Redis's own clock: the same
budget on every web process and host) that holds up to the budget's records and refills at
records/period a second. A read of n records takes n at once if the bucket holds them;
otherwise it is refused whole (CheckBudgetExceeded, 429, with the seconds until it would fit)
and takes nothing. When Redis cannot count, reads are checked uncounted, as the API's and the
pages' rate limits do.

A read's batches carry its run id, whose key lives while the web waits for them (refreshed as
it starts waiting for each batch, expiring VERIFY_TIMEOUT + RUN_KEY_SLACK after): a worker
runs a batch only while its key lives, and gives the batch's records back to the caller's
budget otherwise, so that a read whose request gave up (a batch not answered in
VERIFY_TIMEOUT, its client gone: opening.py; or the web process gone) costs what it checked,
not what it queued.
"""

import logging
import math
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from django.conf import settings
from redis.exceptions import RedisError

from core.rates import rate_parse
from core.redis_client import get_redis, redis_key
from sharing.errors import CheckBudgetExceeded

logger = logging.getLogger(__name__)

# A run's key outlives the web's wait for its next answer by this much.
RUN_KEY_SLACK = 5

# KEYS[1]: the caller's bucket; ARGV: its capacity, its refill a second, the records taken (a
# negative number gives them back). Answers {taken (1 or 0), records left, seconds until the
# records asked for would fit}, numbers as text (Lua's numbers reach Redis as integers).
_TAKE = """
local capacity = tonumber(ARGV[1])
local rate = tonumber(ARGV[2])
local records = tonumber(ARGV[3])
local clock = redis.call('TIME')
local now = tonumber(clock[1]) + tonumber(clock[2]) / 1000000
local state = redis.call('HMGET', KEYS[1], 'left', 'at')
local left = capacity
if state[1] then
  left = math.min(capacity, tonumber(state[1]) + (now - tonumber(state[2])) * rate)
end
if records > left then
  return {0, tostring(left), tostring((records - left) / rate)}
end
left = math.min(capacity, left - records)
redis.call('HSET', KEYS[1], 'left', tostring(left), 'at', tostring(now))
redis.call('EXPIRE', KEYS[1], math.ceil((capacity - left) / rate) + 1)
return {1, tostring(left), '0'}
"""


@dataclass(frozen=True)
class CheckBudget:
    """CHECK_BUDGET: `records` checked at most per `seconds`, all of them at once if need be."""

    records: int
    seconds: int

    @classmethod
    def configured(cls) -> "CheckBudget | None":
        """The budget in settings; None when CHECK_BUDGET is empty (no budget)."""
        if not settings.CHECK_BUDGET:
            return None
        return cls(*rate_parse(settings.CHECK_BUDGET))

    @property
    def refill(self) -> float:
        """Records given back to a caller's budget a second."""
        return self.records / self.seconds


def _bucket_key(caller_id: int) -> str:
    return redis_key("check-budget", caller_id)


def _take(budget: CheckBudget, caller_id: int, records: int) -> tuple[bool, float, float]:
    """(taken, records left, seconds until `records` would fit) of the caller's bucket."""
    script = get_redis().register_script(_TAKE)
    taken, left, wait = script(
        keys=[_bucket_key(caller_id)], args=[budget.records, budget.refill, records]
    )
    return bool(int(taken)), float(left), float(wait)


def checks_charge(*, caller_id: int, records: int) -> None:
    """Take `records` checks from the caller's budget, or raise CheckBudgetExceeded (429, its
    retry_after the seconds until they would fit) and take nothing."""
    budget = CheckBudget.configured()
    if budget is None or records <= 0:
        return
    try:
        taken, left, wait = _take(budget, caller_id, records)
    except (RedisError, OSError) as exc:
        logger.warning("integrity checks not counted, Redis is unavailable: %s", exc)
        return
    if taken:
        return
    retry_after = max(1, math.ceil(wait))
    asked = f"this read checks {records} record{'s' if records != 1 else ''}"
    what = (
        f"{asked}, more than the whole budget of {budget.records} every {budget.seconds} s: "
        "ask for a shorter range"
        if records > budget.records
        else f"{asked} and {math.floor(left)} of your budget of {budget.records} every "
        f"{budget.seconds} s are left: retry in {retry_after} s"
    )
    raise CheckBudgetExceeded(
        f"integrity checks over budget: {what}",
        retry_after=retry_after if records <= budget.records else budget.seconds,
    )


def checks_refund(*, caller_id: int, records: int) -> None:
    """Give back to the caller's budget checks it was charged for that did not run."""
    budget = CheckBudget.configured()
    if budget is None or records <= 0:
        return
    try:
        _take(budget, caller_id, -records)
    except (RedisError, OSError) as exc:
        logger.warning("integrity checks not given back, Redis is unavailable: %s", exc)


@dataclass(frozen=True)
class CheckRun:
    """One read's checks: the records charged to its caller, and the run id its batches carry
    to the workers (None when Redis could not hold it: the batches then run whatever happens)."""

    caller_id: int
    id: str | None

    def waiting(self) -> None:
        """The web waits for a batch (up to VERIFY_TIMEOUT): the batches not run yet stay wanted
        that long."""
        if self.id is not None:
            try:
                get_redis().expire(_run_key(self.id), _run_key_ttl())
            except (RedisError, OSError) as exc:
                logger.warning("a read's checks not kept wanted, Redis is unavailable: %s", exc)

    def refund(self, records: int) -> None:
        """Records of the run that will not be checked (their batch could not be queued)."""
        checks_refund(caller_id=self.caller_id, records=records)


def _run_key(run: str) -> str:
    return redis_key("check-run", run)


def _run_key_ttl() -> int:
    return math.ceil(settings.VERIFY_TIMEOUT) + RUN_KEY_SLACK


@contextmanager
def check_run(*, caller_id: int, records: int) -> Iterator[CheckRun]:
    """The records charged to the caller (CheckBudgetExceeded before anything else), and their
    run key while the block waits for their checks; once it is left, whatever of the run has
    not started yet is not run (the workers give it back to the budget)."""
    checks_charge(caller_id=caller_id, records=records)
    run: str | None = uuid.uuid4().hex
    try:
        get_redis().set(_run_key(run), caller_id, ex=_run_key_ttl())
    except (RedisError, OSError) as exc:
        logger.warning("a read's checks cannot be cancelled, Redis is unavailable: %s", exc)
        run = None
    try:
        yield CheckRun(caller_id, run)
    finally:
        if run is not None:
            try:
                get_redis().delete(_run_key(run))
            except (RedisError, OSError) as exc:
                logger.warning("a read's queued checks not cancelled: %s", exc)


def check_run_wanted(*, run: str | None, caller_id: int, records: int) -> bool:
    """In the worker, before a batch: whether its read still waits for it (a batch without a
    run key always runs). A batch nobody waits for gives its records back to the caller."""
    if run is None:
        return True
    try:
        wanted = bool(get_redis().exists(_run_key(run)))
    except (RedisError, OSError) as exc:
        logger.warning("a batch's run not looked up, Redis is unavailable: %s", exc)
        return True
    if not wanted:
        logger.info("a batch of %s records not checked: its read stopped waiting", records)
        checks_refund(caller_id=caller_id, records=records)
    return wanted
