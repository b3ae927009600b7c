"""stack/webserver.py: granian whose replacements stop the old process only once the new one
listens. A single process that takes seconds to load is replaced over and over while a client
connects all the time: no connection is ever refused (granian's fixed sleep refused them)."""

import hashlib
import inspect
import os
import socket
import subprocess
import threading
import time
from pathlib import Path

import granian.server.common
import psutil
import requests

from stack.anvil import free_port
from stack.processes import PYTHON, REPO_ROOT
from stack.webserver import listening
from tests.stack import wait_for

# Seconds each process of the test's app takes to load: longer than the respawn interval given
# below, which granian alone would sleep before stopping the process being replaced.
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


def test_a_slow_loading_process_is_replaced_without_refusing_a_connection(tmp_path: Path):
    (tmp_path / "slow_app.py").write_text(SLOW_APP)
    port = free_port()
    log = (tmp_path / "web.log").open("wb")
    server = subprocess.Popen(
        [
            PYTHON,
            "-m",
            "stack.webserver",
            "slow_app:application",
            "--interface",
            "wsgi",
            "--working-dir",
            str(tmp_path),
            "--host",
            "127.0.0.1",
            "--port",
            str(port),
            "--workers",
            "1",
            "--no-ws",
            # every sample finds the process over 1 MiB: it is replaced again and again
            "--workers-max-rss",
            "1",
            "--rss-sample-interval",
            "1",
            "--respawn-interval",
            "30",
            "--workers-kill-timeout",
            "5",
        ],
        cwd=REPO_ROOT,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    answers: list[str] = []
    stop = threading.Event()

    def connect_all_the_time() -> None:
        while not stop.is_set():
            try:
                answer = requests.get(f"http://127.0.0.1:{port}/", timeout=30)
                answers.append(str(answer.status_code))
            except requests.ConnectionError as exc:
                answers.append(f"{type(exc).__name__}: {exc}")
            time.sleep(0.02)

    try:
        wait_for(
            lambda: any(listening(p.pid, port) for p in psutil.Process(server.pid).children()),
            timeout=60,
            what="the first process to listen",
        )
        client = threading.Thread(target=connect_all_the_time)
        client.start()
        text = ""
        deadline = time.monotonic() + 90
        while text.count("replacement listens after") < 3 and time.monotonic() < deadline:
            time.sleep(0.5)
            text = (tmp_path / "web.log").read_text()
        stop.set()
        client.join(timeout=60)
    finally:
        stop.set()
        server.terminate()
        server.wait(timeout=30)
        log.close()
    text = (tmp_path / "web.log").read_text()
    assert text.count("replacement listens after") >= 3, text[-3000:]
    assert "does not listen" not in text
    assert len(answers) > 100
    failed = [answer for answer in answers if answer != "200"]
    said = f"{len(failed)} of {len(answers)}: {failed[:3]}\n{text[-3000:]}"
    # Never refused: some process listens all the time. (A process told to stop still closes a
    # connection it had taken but not read yet, which a client sends again: rare, allowed.)
    assert [answer for answer in failed if "refused" in answer] == [], said
    assert len(failed) <= len(answers) // 100, said
