"""The Celery application: broker and results in Redis, tasks in each app's tasks.py."""

import logging
import os
import threading

from celery import Celery, signals
from django.db import close_old_connections, connections

from portal.middleware import service_checks_run

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

logger = logging.getLogger(__name__)
# A worker that refuses to start exits with this status (sysexits.h EX_CONFIG).
EXIT_MISCONFIGURED = 78

# Tasks a person is waiting for, answered from the verify queue (see settings).
VERIFY_TASKS = frozenset({"sharing.tasks.records_verify"})


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
    connections in a forked child: chainworker.chain.rpc_session)."""
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
