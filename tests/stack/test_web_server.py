"""The portal's web server as `make run` runs it (stack/processes.py, `web_server`): granian
replaces a web process that holds too much memory, one at a time, while robots upload, and no
upload is lost or refused on the way."""

import base64
import threading
import time

import psutil
import pytest
import requests

from sharing.models import Record
from tests.chainworker.test_worker_reliability import _robots
from tests.stack import wait_for

pytestmark = [
    pytest.mark.worker,
    pytest.mark.anvil,
    pytest.mark.slow,
    pytest.mark.django_db(transaction=True),
]

UPLOADERS = 4
RECYCLE_LOG = "RSS over threshold, gracefully respawning"


def _web_processes(stack) -> set[int]:
    """The pids of the web server's worker processes (the children of its main process)."""
    return {child.pid for child in psutil.Process(stack.children["web"].pid).children()}


def test_web_processes_over_their_memory_limit_are_replaced_while_uploads_go_on(worker_stack):
    stack = worker_stack(workers=1)
    setups = _robots(UPLOADERS)
    # A limit of 1 MiB, sampled every second: every process is over it at every sample, so
    # the processes are replaced one after another for as long as the uploads run.
    stack.start_web(
        workers=2, max_rss_mib=1, env={**stack.env(), "GRANIAN_RSS_SAMPLE_INTERVAL": "1"}
    )
    first = _web_processes(stack)
    answers: list[int | str] = []
    stop = threading.Event()

    def upload(setup) -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            envelope = base64.b64encode(setup.seal(seq)).decode()
            try:
                # A connection of its own each time, as each of a fleet's agents has.
                answer = requests.post(
                    f"{stack.web_url}/api/v1/records/",
                    json={"envelopes": [envelope]},
                    headers={"Authorization": f"Token {setup.token}", "Connection": "close"},
                    timeout=60,
                )
                answers.append(answer.status_code)
            except requests.RequestException as exc:
                answers.append(f"{type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=upload, args=(setup,)) for setup in setups]
    for thread in threads:
        thread.start()
    try:
        wait_for(
            lambda: not (first & _web_processes(stack)),
            timeout=90,
            what="both web processes replaced",
            interval=0.5,
        )
        time.sleep(2)  # and a moment of uploads to the new ones
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=90)
    log = (stack.logs / "web.log").read_text()
    assert log.count(RECYCLE_LOG) >= 2
    assert [a for a in answers if a != 201] == []
    assert len(answers) > 50
    assert Record.objects.count() == len(answers)
