"""gunicorn's server hooks for the portal's web server (`gunicorn -c python:stack.gunicorn_config`,
as stack/processes.py `web_server` runs it); every other setting is on its command line.

- on_starting: the master, before it forks any worker, empties the web's metrics folder
  (PROMETHEUS_MULTIPROC_DIR): counts of a previous run, under process ids that may come
  again, must not be added to this run's (core/metrics.py).
- child_exit: a worker that exited (replaced after --max-requests, or crashed) hands back its
  live-gauge files, as prometheus-client's multiprocess mode asks.

gunicorn's own lines (a worker booted, replaced, timed out) are written as the portal's are
(`logconfig_dict`: core/logging.py, LOG_FORMAT and LOG_LEVEL as the settings read them), so a
web log is all JSON lines in production.
"""

from __future__ import annotations

import os
from typing import Any

from prometheus_client import multiprocess

from core.logging import logging_config
from core.metrics import metrics_folder_reset, multiproc_folder

_LEVEL = os.environ.get("LOG_LEVEL") or "INFO"
logconfig_dict = logging_config(log_format=os.environ.get("LOG_FORMAT") or "json", level=_LEVEL)
# gunicorn's own logger, named so that its plain handler is replaced by the portal's.
logconfig_dict["loggers"]["gunicorn.error"] = {
    "handlers": ["default"],
    "level": _LEVEL,
    "propagate": False,
}


def on_starting(server: Any) -> None:
    metrics_folder_reset()


def child_exit(server: Any, worker: Any) -> None:
    folder = multiproc_folder()
    if folder is not None:
        multiprocess.mark_process_dead(worker.pid, str(folder))
