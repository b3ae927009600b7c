"""stack/webserver.py: granian whose replacements stop the old process only once the new one
listens. A single process that takes seconds to load is replaced over and over while a client
connects all the time: no connection is ever refused (granian's fixed sleep refused them)."""

import hashlib
import inspect
import os
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

import granian.server.common
import psutil
import pytest
import requests

from stack.anvil import free_port
from stack.processes import PYTHON, REPO_ROOT
from stack.webserver import listening
from tests.harness import wait_for

pytestmark = pytest.mark.process

# Seconds each process of the test's app takes to load, without a listening socket: a process
# being replaced that stopped before its successor loaded would leave none for that long.
LOAD_SECONDS = 3
SLOW_APP = f"""
import time

time.sleep({LOAD_SECONDS})


def application(environ, start_response):
    start_response("200 OK", [("Content-Type", "text/plain")])
    return [b"ok"]
"""
# granian 2.8.9's AbstractServer._respawn_workers, which stack/webserver.py's copy follows.
GRANIAN_RESPAWN_SHA256 = "164f5281ce938dbef45a3a26eb6a5b3e82aa7855d5e1827de049522370648c4a"


def _serves(server: subprocess.Popen, port: int) -> bool:
    """Whether a process of the server listens on `port`."""
    return any(listening(child.pid, port) for child in psutil.Process(server.pid).children())


def test_listening_sees_only_a_listening_socket_of_that_process():
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        port = server.getsockname()[1]
        assert not listening(os.getpid(), port)  # bound, not listening
        server.listen()
        assert listening(os.getpid(), port)
        assert not listening(os.getpid(), free_port())
    gone = subprocess.Popen([PYTHON, "-c", "pass"])
    gone.wait()
    assert not listening(gone.pid, port)


def test_the_copied_respawn_follows_the_installed_granian():
    """If granian's own replacement changed, the copy in stack/webserver.py must be looked at."""
    source = inspect.getsource(granian.server.common.AbstractServer._respawn_workers)
    assert hashlib.sha256(source.encode()).hexdigest() == GRANIAN_RESPAWN_SHA256, source


@contextmanager
def _one_process_server(
    tmp_path: Path, app: str, *, respawn_interval: int, kill_timeout: int
) -> Iterator[tuple[subprocess.Popen, int]]:
    """`python -m stack.webserver` serving `app` (a module in tmp_path, `app:application`) with
    one process, which every RSS sample finds over its 1 MiB limit: it is replaced again and
    again. Its log is tmp_path/web.log; the server and every process it started are gone after."""
    port = free_port()
    with (tmp_path / "web.log").open("wb") as log:
        server = subprocess.Popen(
            [
                *(PYTHON, "-m", "stack.webserver", f"{app}:application", "--interface", "wsgi"),
                *("--working-dir", str(tmp_path), "--host", "127.0.0.1", "--port", str(port)),
                *("--workers", "1", "--no-ws", "--workers-max-rss", "1"),
                *("--rss-sample-interval", "1", "--respawn-interval", str(respawn_interval)),
                *("--workers-kill-timeout", str(kill_timeout)),
            ],
            cwd=REPO_ROOT,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            wait_for(lambda: _serves(server, port), timeout=60, what="the first process to listen")
            yield server, port
        finally:
            with suppress(ProcessLookupError):
                os.killpg(server.pid, signal.SIGKILL)
            server.wait()


def test_a_slow_loading_process_is_replaced_without_refusing_a_connection(tmp_path: Path):
    (tmp_path / "slow_app.py").write_text(SLOW_APP)
    answers: list[str] = []
    stop = threading.Event()
    server = _one_process_server(tmp_path, "slow_app", respawn_interval=30, kill_timeout=5)
    with server as (_, port):

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
                lambda: (tmp_path / "web.log").read_text().count("replacement listens after") >= 3,
                timeout=90,
                what="three replacements",
                interval=0.5,
            )
        finally:
            stop.set()
            client.join(timeout=60)
    text = (tmp_path / "web.log").read_text()
    assert "does not listen" not in text
    assert len(answers) > 100
    failed = [answer for answer in answers if answer != "200"]
    said = f"{len(failed)} of {len(answers)}: {failed[:3]}\n{text[-3000:]}"
    # Never refused: some process listens all the time. (A process told to stop still closes a
    # connection it had taken but not read yet, which a client sends again: rare, allowed.)
    assert [answer for answer in failed if "refused" in answer] == [], said
    assert len(failed) <= len(answers) // 100, said


# Loads at once the first time, never after: the replacement of the first process hangs.
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


def test_a_server_told_to_stop_does_not_wait_for_a_replacement(tmp_path: Path):
    """SIGTERM while a replacement loads (and would for an hour): the server stops at once
    rather than wait out --respawn-interval (an hour)."""
    (tmp_path / "hanging_app.py").write_text(HANGING_SUCCESSOR)
    server = _one_process_server(tmp_path, "hanging_app", respawn_interval=3600, kill_timeout=3)
    with server as (process, port):
        wait_for(
            lambda: "Respawning worker-1" in (tmp_path / "web.log").read_text(),
            timeout=60,
            what="a replacement to start",
        )
        assert requests.get(f"http://127.0.0.1:{port}/", timeout=10).status_code == 200
        process.terminate()
        process.wait(timeout=60)  # TimeoutExpired if it waits for the replacement
    assert "does not listen" not in (tmp_path / "web.log").read_text()
