"""The portal's web server as `make run` runs it (stack/processes.py, `web_server`): gunicorn
replaces each worker process after its --max-requests while robots upload, and no upload is
lost or refused on the way; a worker that dies is started again."""

import base64
import threading

import psutil
import pytest
import requests

from sharing.models import Record
from tests.support.harness import wait_for
from tests.support.worker_robots import registered_robots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]

UPLOADERS = 4
RESENDS = 3
RECYCLE_LOG = "Autorestarting worker after current request"
# Requests each worker serves before it is replaced: both are replaced within seconds here.
MAX_REQUESTS = 25


def _upload_one(stack, setup, envelope: bytes) -> requests.Response:
    """The robot's sealed envelope POSTed on a connection of its own, as each agent of a fleet
    has one."""
    return requests.post(
        f"{stack.web_url}/api/v1/records/",
        json={"envelopes": [base64.b64encode(envelope).decode()]},
        headers={"Authorization": f"Token {setup.token}", "Connection": "close"},
        timeout=60,
    )


def test_web_processes_are_replaced_after_their_requests_while_uploads_go_on(worker_stack):
    stack = worker_stack(workers=1)
    setups = registered_robots(UPLOADERS)
    # Every worker is replaced after MAX_REQUESTS requests (and again, and again) for as long as
    # the uploads run. The robots upload as fast as they are answered: no rate limit here.
    unlimited = {"API_RATE_UPLOAD": "1000000/minute", "API_RATE_USER": "1000000/minute"}
    stack.start_web(workers=2, max_requests=MAX_REQUESTS, env={**stack.env(), **unlimited})
    first = stack.web_processes()
    answers: list[int] = []  # the answer each upload got in the end
    dropped: list[str] = []  # connections closed without an answer, each sent again
    stop = threading.Event()

    def upload(setup) -> None:
        seq = 0
        while not stop.is_set():
            seq += 1
            envelope = setup.seal(seq)
            for _ in range(RESENDS + 1):  # as the agent does: the same envelope again
                try:
                    answer = _upload_one(stack, setup, envelope)
                except requests.ConnectionError as exc:
                    dropped.append(f"{type(exc).__name__}: {exc}")
                    continue
                answers.append(answer.status_code)
                break
            else:
                answers.append(0)

    threads = [threading.Thread(target=upload, args=(setup,)) for setup in setups]
    for thread in threads:
        thread.start()
    try:
        wait_for(
            lambda: not (first & stack.web_processes()),
            timeout=120,
            what="both web processes replaced",
            interval=0.5,
        )
        # and uploads to the new ones, which are replaced in turn
        wait_for(
            lambda: len(answers) >= 4 * MAX_REQUESTS,
            timeout=120,
            what="uploads to the replacements",
            interval=0.5,
        )
    finally:
        stop.set()
        for thread in threads:
            thread.join(timeout=120)
    log = (stack.logs / "web.log").read_text()
    events = "\n".join(line for line in log.splitlines() if "portal.access" not in line)
    assert log.count(RECYCLE_LOG) >= 2
    assert len(answers) >= 4 * MAX_REQUESTS
    # Every upload stored, once, and answered 201: the master holds the listening socket, so a
    # worker being replaced refuses nothing, and one that stops finishes what it took first.
    refused = [a for a in answers if a != 201]
    said = f"{len(answers)} uploads; dropped {dropped[:3]}\n{events[-6000:]}"
    assert refused == [], f"{refused[:3]} of {said}"
    assert dropped == [], said
    assert Record.objects.count() == len(answers)


def test_a_web_process_that_dies_is_started_again(worker_stack):
    """A web process killed outright (an OOM kill, a crash in a C library) is replaced; the
    portal answers on through the others meanwhile and on the new one after."""
    stack = worker_stack(workers=1)
    setup = registered_robots(1)[0]
    stack.start_web(workers=2)  # returns once both processes run
    victim = min(stack.web_processes())
    psutil.Process(victim).kill()
    wait_for(lambda: victim not in stack.web_processes(), timeout=10, what="the kill to land")
    for seq in range(1, 6):  # meanwhile the other one serves
        answer = _upload_one(stack, setup, setup.seal(seq))
        assert answer.status_code == 201, answer.text
    wait_for(
        lambda: len(stack.web_processes()) == 2 and victim not in stack.web_processes(),
        timeout=60,
        what="the killed web process replaced",
        interval=0.5,
    )
    for seq in range(6, 26):  # new connections, spread over both processes
        answer = _upload_one(stack, setup, setup.seal(seq))
        assert answer.status_code == 201, answer.text
    assert stack.children["web"].running()
