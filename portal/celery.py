"""The Celery application: broker and results in Redis, tasks in each app's tasks.py.

Its signals carry the web request's id into the tasks it queues (a message header, then the
log context of the task's run: core/logging.py), count every finished task for /metrics
(portal/metrics.py), and empty a worker's metrics folder as it starts (core/metrics.py).
"""

import gc
import logging
import os
import threading
from contextlib import suppress
from contextvars import Token
from typing import Any

from celery import Celery, signals
from django.db import close_old_connections, connections

from core.logging import current_request_id, log_context_reset, log_context_set
from core.metrics import metrics_folder_reset
from portal.metrics import task_observed
from portal.middleware import service_checks_run

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

logger = logging.getLogger(__name__)
# A worker that refuses to start exits with this status (sysexits.h EX_CONFIG).
EXIT_MISCONFIGURED = 78

# Tasks a person is waiting for, answered from the verify queue (see settings).
VERIFY_TASKS = frozenset({"sharing.tasks.records_verify", "sharing.tasks.series_verify"})


def route_task(name, args, kwargs, options, task=None, **kw):
    """Views' integrity checks to "<default queue>-verify", read when sent: tests change the
    default queue at run time."""
    if name in VERIFY_TASKS:
        return {"queue": app.conf.task_default_queue + app.conf.verify_queue_suffix}
    return None


app = Celery("portal")
app.config_from_object("django.conf:settings", namespace="CELERY")
app.conf.task_routes = (route_task,)
app.autodiscover_tasks()


@signals.task_prerun.connect
@signals.task_postrun.connect
def task_connections_tidy(**kwargs: object) -> None:
    """Around every task, what Django does around every request: close a connection that
    failed or is older than CONN_MAX_AGE (settings.CELERY_DB_REUSE_MAX keeps Celery from
    closing each one); with DATABASE_CONN_MAX_AGE=0 that is every one, as before."""
    task = kwargs.get("task")
    if not getattr(getattr(task, "request", None), "is_eager", False):
        close_old_connections()


# The message header that carries the id of the request (or task) that queued a task.
REQUEST_ID_HEADER = "authros_request_id"
_task_contexts: dict[str, Token] = {}


@signals.before_task_publish.connect
def task_request_id_attach(headers: dict[str, Any] | None = None, **kwargs: object) -> None:
    """The id of the request (or the task) queueing this task goes with it."""
    request_id = current_request_id()
    if request_id is not None and headers is not None:
        headers[REQUEST_ID_HEADER] = request_id


@signals.task_prerun.connect
def task_log_context_start(task_id: str = "", task: Any = None, **kwargs: object) -> None:
    """Every line the task logs names it and the request that queued it."""
    request = getattr(task, "request", None)
    request_id = (
        getattr(request, REQUEST_ID_HEADER, None)
        or (getattr(request, "headers", None) or {}).get(REQUEST_ID_HEADER)
        or current_request_id()  # a task run inline, in the request's own thread
    )
    _task_contexts[task_id] = log_context_set(
        request_id=request_id, task=getattr(task, "name", None), task_id=task_id
    )


@signals.task_postrun.connect
def task_finished(
    task_id: str = "", task: Any = None, retval: Any = None, state: str = "", **kwargs: object
) -> None:
    task_observed(getattr(task, "name", "unknown"), state or "UNKNOWN", retval)
    context = _task_contexts.pop(task_id, None)
    if context is not None:
        # A pool that ran the task in another context (threads) has nothing to reset here.
        with suppress(ValueError):
            log_context_reset(context)


@signals.worker_init.connect
def worker_metrics_folder_reset(**kwargs: object) -> None:
    """The worker's main process, before it forks its pool: last run's counts go."""
    metrics_folder_reset()


@signals.worker_process_init.connect
def worker_heap_freeze(**kwargs: object) -> None:
    """A pool process, once made: what the worker built before its first task (modules, the
    app, the settings: about 300,000 objects) lives as long as the process, so it leaves the
    collector's sight, as the web's warm-up does (portal/wsgi.py). A series' slice makes a few
    hundred thousand short-lived objects; each full collection walked the whole heap with
    them (about a fifth of a slice's CPU, bench/REPORT.md), now only what the tasks made."""
    gc.collect()
    gc.freeze()


@signals.worker_init.connect
def worker_refuse_misconfigured(**kwargs: object) -> None:
    """A worker does not start while the service checks fail (portal/middleware.py): it logs
    why and exits, so that no task runs under a wrong master key or operator key."""
    problems = _service_problems_in_own_thread()
    for problem in problems:
        logger.error("the worker refuses to start until an operator fixes this: %s", problem)
    if problems:
        raise SystemExit(EXIT_MISCONFIGURED)


def _service_problems_in_own_thread() -> list[str]:
    """The checks, in a thread of their own: the database connection they open is not reused
    by the pool's processes forked from this one (the chain node's session drops its
    connections in a forked child: chainworker.rpc.rpc_session)."""
    outcome: list[str] = []

    def check() -> None:
        try:
            problems, unchecked = service_checks_run()
        except Exception:
            logger.warning("the worker could not check its secrets; starting", exc_info=True)
            return
        finally:
            connections.close_all()
        outcome.extend(problems)
        for note in unchecked:
            logger.warning("%s", note)

    thread = threading.Thread(target=check, name="service-checks")
    thread.start()
    thread.join()
    return outcome
