"""Queueing tasks by name, so that services never import task modules (tasks import services).

A message that cannot be queued is not lost: the row it is about stays pending and the
periodic sweep queues it again. Tests about logic run tasks eagerly (inline) instead.
"""

import logging
from functools import cache
from typing import Any

from celery import Celery, current_app
from celery.result import AsyncResult
from kombu.exceptions import OperationalError
from redis.exceptions import RedisError

logger = logging.getLogger(__name__)

_QUICK_RETRY = {"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5, "interval_max": 1}


def dispatch(
    task_name: str, *args: Any, countdown: float | None = None, keep_result: bool = True
) -> AsyncResult:
    """Send the task named `task_name` (as registered with Celery); its pending result.

    Without `keep_result` nobody waits for it: the result is not stored, and this process
    does not listen for it (the Redis result backend subscribes to every result it may be
    asked for, a subscription and a message per task otherwise).
    Raises kombu's OperationalError, RedisError or OSError when the broker cannot take it.
    """
    app = current_app
    if app.conf.task_always_eager:
        # send_task ignores task_always_eager: run the registered task inline instead.
        _tasks_imported(app)
        return app.tasks[task_name].apply_async(args=args, countdown=countdown)
    return app.send_task(
        task_name,
        args=args,
        countdown=countdown,
        retry=True,
        retry_policy=_QUICK_RETRY,
        ignore_result=not keep_result,
    )


@cache
def _tasks_imported(app: Celery) -> None:
    """Import the apps' task modules once per process, as a worker does when it starts (each
    import runs Celery's Django fixup, which runs every system check: 50 ms a task)."""
    app.loader.import_default_modules()


def enqueue(task_name: str, *args: Any, countdown: float | None = None) -> bool:
    """Queue the task named `task_name`, whose result nobody waits for; False if the broker
    cannot take it now."""
    try:
        dispatch(task_name, *args, countdown=countdown, keep_result=False)
    except (OperationalError, RedisError, OSError) as exc:
        logger.warning(
            "could not queue %s%s (%s); the sweep will queue it again", task_name, args, exc
        )
        return False
    return True
