"""A single record's check without Celery's round trip: the web asks a verify worker through a
Redis list, and the worker answers on a key of the request's own.

A view of one record (`record_open`) waited about 13 ms of Celery for a check of about 6: the
message's encoding and routing, the worker's prefetch and acknowledgement, the result backend's
publish and subscription. Here the web RPUSHes the task's arguments as JSON to one list, any
verify worker (on any host) BLPOPs it, runs the very function of the task
`sharing.tasks.records_verify` in its own process (the check is the worker's, as before: the
web never checks and nothing is remembered as held), and RPUSHes its answer, the same JSON as
the task's result (the envelope it checked, ciphertext, never a plaintext), to the request's
answer key, which expires once nobody reads it. Every serving worker keeps a presence key
alive; without one (none started yet, or all stopped) the web sends the Celery task instead,
so a portal whose workers do not serve here works as before. Each request is taken by one
worker: a list is the queue, shared by every host.
"""

import json
import logging
import threading
import time
import uuid
from collections.abc import Callable
from typing import Any

from celery.exceptions import TimeoutError as CeleryTimeoutError
from django.db import connections
from redis.exceptions import RedisError

from accounts.errors import IdentityMismatch
from core.logging import current_request_id, log_context_reset, log_context_set
from core.redis_client import get_redis, redis_key

logger = logging.getLogger(__name__)

# A serving worker says it is there for this long, renewed at least every POLL_SECONDS.
PRESENCE_SECONDS = 5
# Each blocking read waits at most this long (under the Redis client's socket timeout).
POLL_SECONDS = 1.0
# An answer nobody reads (the web gave up) is gone after this long.
ANSWER_SECONDS = 60
_IDENTITY = "identity_mismatch"
# The task whose function a direct check runs, as its log lines name it.
DIRECT_TASK = "sharing.tasks.records_verify"


def _requests_key() -> str:
    return redis_key("verify", "direct", "requests")


def _presence_key() -> str:
    return redis_key("verify", "direct", "serving")


def _answer_key(request_id: str) -> str:
    return redis_key("verify", "direct", "answer", request_id)


class DirectCheck:
    """A check asked of a verify worker through Redis: `get` waits for its answer as Celery's
    AsyncResult.get does (its exceptions: IdentityMismatch as the worker raised it, Celery's
    TimeoutError, so that the web's wait in slices (opening._answer_while_wanted) goes on,
    RuntimeError for the worker's own failure, RedisError); `forget` drops an unread answer."""

    def __init__(self, request_id: str) -> None:
        self.request_id = request_id

    def get(self, timeout: float, **_celery_options: object) -> Any:
        client = get_redis()
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            found = client.blpop([_answer_key(self.request_id)], timeout=min(POLL_SECONDS, left))
            if found is not None:
                return _answer_read(found[1])
        raise CeleryTimeoutError(f"no verify worker answered in {timeout:g} s")

    def forget(self) -> None:
        get_redis().delete(_answer_key(self.request_id))


def direct_checks_served() -> bool:
    """Whether a verify worker (of any host) serves direct checks now."""
    return bool(get_redis().exists(_presence_key()))


def direct_check_send(*task_args: Any) -> DirectCheck | None:
    """Ask a verify worker for the check `sharing.tasks.records_verify(*task_args)`; None (send
    the task instead) when no worker serves here now. RedisError if Redis cannot take it."""
    if not direct_checks_served():
        return None
    client = get_redis()
    request_id = uuid.uuid4().hex
    request = {"id": request_id, "args": list(task_args), "request_id": current_request_id()}
    client.rpush(_requests_key(), json.dumps(request))
    return DirectCheck(request_id)


def direct_checks_serve(run: Callable[..., Any], stop: threading.Event) -> None:
    """Answer the web's checks until `stop` is set: each request's arguments given to `run`
    (the task's own function), its answer (or its refusal) pushed to the request's key. Redis
    out of reach is waited out; a check that fails is answered as failed, and logged."""
    client = get_redis()
    while not stop.is_set():
        try:
            client.set(_presence_key(), "1", ex=PRESENCE_SECONDS)
            found = client.blpop([_requests_key()], timeout=POLL_SECONDS)
        except RedisError as exc:
            logger.warning("direct checks: Redis out of reach (%s); trying again", exc)
            stop.wait(POLL_SECONDS)
            continue
        if found is None:
            continue
        try:
            request = json.loads(found[1])
            request_id, args = str(request["id"]), list(request["args"])
        except (ValueError, KeyError, TypeError):
            logger.warning("direct checks: a request that is not one was dropped")
            continue
        # Its lines name the task and the web request that asked, as a task's do (portal/celery.py).
        context = log_context_set(
            request_id=request.get("request_id"), task=DIRECT_TASK, task_id=request_id
        )
        try:
            answer = _checked(run, args)
            logger.info("direct check of %s records answered", len(args[0]) if args else 0)
        finally:
            log_context_reset(context)
        try:
            with client.pipeline(transaction=False) as pipe:
                pipe.rpush(_answer_key(request_id), json.dumps(answer))
                pipe.expire(_answer_key(request_id), ANSWER_SECONDS)
                pipe.execute()
        except RedisError as exc:  # the web waits out its timeout: verification unavailable
            logger.warning("direct checks: the answer to %s was lost: %s", request_id, exc)


def direct_checks_serving(run: Callable[..., Any]) -> threading.Event:
    """Start serving in a daemon thread of this process; set the event returned to stop."""
    stop = threading.Event()
    thread = threading.Thread(
        target=direct_checks_serve, args=(run, stop), name="direct-checks", daemon=True
    )
    thread.start()
    return stop


def _checked(run: Callable[..., Any], args: list[Any]) -> dict[str, Any]:
    """The task's answer to `args`, as JSON: its result, or what refused it."""
    try:
        return {"result": run(*args)}
    except IdentityMismatch as exc:
        return {"error": _IDENTITY, "detail": str(exc)}
    except Exception as exc:  # the check's own failure: the web answers it unavailable
        logger.exception("direct checks: a check failed")
        return {"error": type(exc).__name__, "detail": str(exc)}
    finally:
        connections.close_all()  # this thread's own, as a worker closes them after each task


def _answer_read(raw: bytes) -> Any:
    answer = json.loads(raw)
    if "result" in answer:
        return answer["result"]
    if answer.get("error") == _IDENTITY:
        raise IdentityMismatch(answer.get("detail", ""))
    raise RuntimeError(f"the verify worker failed: {answer.get('error')}: {answer.get('detail')}")
