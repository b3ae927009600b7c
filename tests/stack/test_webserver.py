"""The web server's command line (stack/processes.py `web_server`, gunicorn): its master holds
the listening socket, so a worker replaced after --max-requests, even one whose successor takes
seconds to load, never makes a connection be refused; and a server told to stop does not wait
for a replacement that hangs while loading."""

import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import psutil
import pytest
import requests

from stack.anvil import free_port
from stack.processes import REPO_ROOT, WebSizing, web_server
from tests.support.harness import wait_for

pytestmark = pytest.mark.process

# Seconds each process of the test's app takes to load: while the only worker is replaced, no
# process can take a connection for that long.
LOAD_SECONDS = 3
SLOW_APP = f"""
import os, time

time.sleep({LOAD_SECONDS})
with open(os.path.join(os.path.dirname(__file__), "loads"), "a") as loads:
    loads.write(f"{{os.getpid()}}\\n")


def application(environ, start_response):
    start_response("200 OK", [("Content-Type", "text/plain")])
    return [b"ok"]
"""
REQUESTS_PER_WORKER = 20


@contextmanager
def _one_worker_server(tmp_path: Path, app: str) -> Iterator[tuple[subprocess.Popen, int]]:
    """make run's web server command line serving `app` (a module in tmp_path) with one worker,
    replaced after every REQUESTS_PER_WORKER requests. Its log is tmp_path/web.log; the server
    and every process it started are gone after."""
    port = free_port()
    command = web_server(
        "127.0.0.1",
        port,
        WebSizing(workers=1, threads=2),
        max_requests=REQUESTS_PER_WORKER,
        max_requests_jitter=0,
        app=f"{app}:application",
    )
    with (tmp_path / "web.log").open("wb") as log:
        server = subprocess.Popen(
            [*command, "--pythonpath", str(tmp_path)],
            cwd=REPO_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "metrics" / "web")},
        )
        try:
            wait_for(
                lambda: psutil.Process(server.pid).children(),
                timeout=60,
                what="the first worker",
            )
            yield server, port
        finally:
            with suppress(ProcessLookupError):
                os.killpg(server.pid, signal.SIGKILL)
            server.wait()


def test_a_slow_loading_worker_is_replaced_without_refusing_a_connection(tmp_path: Path):
    (tmp_path / "slow_app.py").write_text(SLOW_APP)
    answers: list[str] = []
    stop = threading.Event()
    with _one_worker_server(tmp_path, "slow_app") as (_, port):

        def connect_all_the_time() -> None:
            while not stop.is_set():
                try:
                    answer = requests.get(f"http://127.0.0.1:{port}/", timeout=30)
                    answers.append(str(answer.status_code))
                except requests.ConnectionError as exc:
                    answers.append(f"{type(exc).__name__}: {exc}")
                time.sleep(0.02)

        client = threading.Thread(target=connect_all_the_time)
        client.start()
        try:
            wait_for(
                lambda: (
                    len((tmp_path / "loads").read_text().split()) >= 4
                    if (tmp_path / "loads").exists()
                    else False
                ),
                timeout=120,
                what="three replacements loaded",
                interval=0.5,
            )
        finally:
            stop.set()
            client.join(timeout=60)
    text = (tmp_path / "web.log").read_text()
    assert text.count("Autorestarting worker after current request") >= 3, text[-3000:]
    assert len(answers) > 3 * REQUESTS_PER_WORKER
    failed = [answer for answer in answers if answer != "200"]
    # Never refused, never dropped: the master holds the socket, and the connections that wait
    # while the only worker loads are served by its successor.
    assert failed == [], f"{len(failed)} of {len(answers)}: {failed[:3]}\n{text[-3000:]}"


# Loads at once the first time, never after: the replacement of the first worker hangs.
HANGING_SUCCESSOR = """
import os, time

MARK = os.path.join(os.path.dirname(__file__), "loaded-once")
if os.path.exists(MARK):
    time.sleep(3600)
open(MARK, "w").close()


def application(environ, start_response):
    start_response("200 OK", [("Content-Type", "text/plain")])
    return [b"ok"]
"""


def test_a_server_told_to_stop_does_not_wait_for_a_hanging_replacement(tmp_path: Path):
    """SIGTERM while a replacement loads (and would for an hour): the server stops within its
    graceful timeout rather than wait for it."""
    (tmp_path / "hanging_app.py").write_text(HANGING_SUCCESSOR)
    with _one_worker_server(tmp_path, "hanging_app") as (process, port):
        for _ in range(REQUESTS_PER_WORKER):
            assert requests.get(f"http://127.0.0.1:{port}/", timeout=10).status_code == 200
        wait_for(
            lambda: (
                "Booting worker" in (tmp_path / "web.log").read_text().split("Autorestarting")[-1]
            ),
            timeout=60,
            what="a replacement to start loading",
        )
        process.terminate()
        process.wait(timeout=60)  # TimeoutExpired if it waits for the replacement


def test_the_master_empties_the_webs_metrics_folder_as_it_starts(tmp_path: Path):
    folder = tmp_path / "metrics" / "web"
    folder.mkdir(parents=True)
    (folder / "counter_4242.db").write_bytes(b"left by a previous run")
    (tmp_path / "slow_app.py").write_text(SLOW_APP)
    with _one_worker_server(tmp_path, "slow_app"):
        wait_for(lambda: not (folder / "counter_4242.db").exists(), timeout=30, what="the reset")
    assert folder.is_dir()
