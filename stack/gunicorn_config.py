"""gunicorn's server hooks for the portal's web server (`gunicorn -c python:stack.gunicorn_config`,
as stack/processes.py `web_server` runs it); every other setting is on its command line.

- on_starting: the master, before it forks any worker, empties the web's metrics folder
  (PROMETHEUS_MULTIPROC_DIR): counts of a previous run, under process ids that may come
  again, must not be added to this run's (core/metrics.py).
- child_exit: a worker that exited (replaced after --max-requests, or crashed) hands back its
  live-gauge files, as prometheus-client's multiprocess mode asks.
"""

from __future__ import annotations

from typing import Any

from prometheus_client import multiprocess

from core.metrics import metrics_folder_reset, multiproc_folder


def on_starting(server: Any) -> None:
    metrics_folder_reset()


def child_exit(server: Any, worker: Any) -> None:
    folder = multiproc_folder()
    if folder is not None:
        multiprocess.mark_process_dead(worker.pid, str(folder))
