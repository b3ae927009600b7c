"""The Celery application: broker and results in Redis, tasks in each app's tasks.py."""

import os

from celery import Celery

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")

# Tasks a person is waiting for, answered from the verify queue (see settings).
VERIFY_TASKS = frozenset({"sharing.tasks.record_verify"})


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
