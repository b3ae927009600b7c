"""Queueing chain work after a commit. A message that cannot be queued is not lost: the
row it is about stays pending and the periodic sweep queues it again."""

import logging
from importlib import import_module
from typing import Any

from kombu.exceptions import OperationalError
from redis.exceptions import RedisError

logger = logging.getLogger(__name__)

_QUICK_RETRY = {"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5, "interval_max": 1}


def enqueue(task_path: str, *args: Any, countdown: float | None = None) -> bool:
    """Queue the task at `task_path` (module.function); False if the broker cannot take it.

    Tasks are named rather than imported so that services never import task modules.
    """
    module_name, _, function_name = task_path.rpartition(".")
    task = getattr(import_module(module_name), function_name)
    try:
        task.apply_async(args=args, countdown=countdown, retry=True, retry_policy=_QUICK_RETRY)
    except (OperationalError, RedisError, OSError) as exc:
        logger.warning(
            "could not queue %s%s (%s); the sweep will queue it again", task_path, args, exc
        )
        return False
    return True
