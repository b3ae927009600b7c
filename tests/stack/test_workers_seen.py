"""Celery workers started as `make run` starts them (stack/processes.py `celery_worker`) are
seen alive by monitoring: they answer `celery -A portal inspect ping`, and send the heartbeats
by which Flower tells a live worker from a dead one; they send task events, so that Flower,
started as docs/operations.md says, lists their tasks; and a worker host serves /metrics on
WORKER_METRICS_PORT, its pool's counts included."""

import json
import re
import shlex
import socket
import subprocess
import time
import uuid

import pytest
import requests
from kombu import Connection
from prometheus_client.parser import text_string_to_metric_families

from portal.celery import app
from stack.anvil import free_port
from stack.processes import PYTHON, REPO_ROOT
from tests.support.harness import wait_for

pytestmark = [pytest.mark.worker, pytest.mark.process, pytest.mark.django_db(transaction=True)]


CELERY = (PYTHON, "-m", "celery", "-A", "portal")


class _Seen(Exception):
    """The heartbeat looked for arrived."""


def test_a_worker_answers_inspect_ping_and_sends_heartbeats(worker_stack, settings):
    stack = worker_stack(workers=0)
    # A name no other test's worker on this Redis has: they would answer a ping of "w0@..." too.
    name = f"ping-{uuid.uuid4().hex[:8]}"
    hostname = f"{name}@{socket.gethostname()}"
    stack.start_worker(name)
    # A ping is a broadcast: one sent before the worker listens reaches nobody.
    wait_for(lambda: f"{hostname} ready" in stack.worker_logs(), timeout=120, what="the worker")
    ping = subprocess.run(
        [*CELERY, "inspect", "ping", "--destination", hostname, "--timeout", "30", "--json"],
        cwd=REPO_ROOT,
        env=stack.env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert ping.returncode == 0, f"{ping.stdout}\n{ping.stderr}\n{stack.worker_logs()[-3000:]}"
    answers = json.loads(ping.stdout.strip().splitlines()[-1])
    assert answers == {hostname: {"ok": "pong"}}

    heartbeats: list[dict] = []

    def on_heartbeat(event: dict) -> None:
        if event.get("hostname") != hostname:
            return
        heartbeats.append(event)
        # The stack's beat sends its sweeps at start, so a heartbeat may count one running:
        # an idle one comes once they are done (each takes milliseconds).
        if event.get("active") == 0:
            raise _Seen

    with Connection(settings.CELERY_BROKER_URL) as connection:
        receiver = app.events.Receiver(connection, handlers={"worker-heartbeat": on_heartbeat})
        with pytest.raises(_Seen):
            receiver.capture(limit=None, timeout=60, wakeup=False)
    assert heartbeats[-1]["active"] == 0
    assert all(isinstance(beat["active"], int) and beat["active"] >= 0 for beat in heartbeats)


# A task no beat schedule sends within the test (hourly), cheap, with no arguments.
PROBE_TASK = "accounts.tasks.robot_pairings_purge"
EVENTS_WAIT = 90.0  # seconds
FLOWER_COMMAND = re.compile(r"`\.venv/bin/(celery -A portal flower [^`]*)`")


def _flower_as_documented(port: int) -> list[str]:
    """docs/operations.md's command for Flower, on `port`."""
    (command,) = FLOWER_COMMAND.findall((REPO_ROOT / "docs" / "operations.md").read_text())
    argv = shlex.split(command)
    assert "--port=5555" in argv
    return [PYTHON, "-m", *[f"--port={port}" if a == "--port=5555" else a for a in argv]]


def _flower_state(url: str, task_id: str) -> str | None:
    try:
        answer = requests.get(f"{url}/api/task/info/{task_id}", timeout=10)
    except requests.RequestException:
        return None
    return answer.json().get("state") if answer.status_code == 200 else None


def _answers(url: str) -> bool:
    try:
        return requests.get(url, timeout=5).status_code == 200
    except requests.RequestException:
        return False


def _samples(url: str) -> dict[tuple[str, tuple], float]:
    answer = requests.get(url, timeout=30)
    assert answer.status_code == 200, answer.text
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(answer.text)
        for sample in family.samples
    }


@pytest.mark.timeout(600)  # the deadline below fails it first
def test_a_worker_sends_task_events_and_its_host_serves_metrics(worker_stack, settings, tmp_path):
    stack = worker_stack(workers=0)
    name = f"events-{uuid.uuid4().hex[:8]}"
    hostname = f"{name}@{socket.gethostname()}"
    port = free_port()
    env = {
        **stack.env(),
        "WORKER_METRICS_PORT": str(port),
        "PROMETHEUS_MULTIPROC_DIR": str(tmp_path / "metrics" / "worker"),
    }
    flower = f"http://127.0.0.1:{free_port()}"
    stack.children.spawn(
        "flower",
        _flower_as_documented(int(flower.rsplit(":", 1)[1])),
        env={**stack.env(), "FLOWER_UNAUTHENTICATED_API": "true"},
    )
    stack.start_worker(name, env=env)
    # Flower listens before the task is sent (below, at the worker's first heartbeat).
    wait_for(lambda: _answers(f"{flower}/healthcheck"), timeout=60, what="Flower to answer")
    sent: list[str] = []
    seen: dict[str, set[str]] = {}

    # The worker's heartbeats keep the capture from timing out by itself (they are events
    # too, every 2 s): a worker that sends no task events fails the test at this deadline.
    deadline = time.monotonic() + EVENTS_WAIT

    def on_event(event: dict) -> None:
        if time.monotonic() > deadline:
            raise AssertionError(f"no task-succeeded within {EVENTS_WAIT:g} s; seen: {seen}")
        # The worker listens once it sends heartbeats: only then is the task sent.
        if event["type"] == "worker-heartbeat" and event.get("hostname") == hostname and not sent:
            sent.append(app.send_task(PROBE_TASK).id)
        if sent and event.get("uuid") == sent[0]:
            seen.setdefault(event["type"], set()).add(event.get("hostname", ""))
            if event["type"] == "task-succeeded":
                raise _Seen

    with Connection(settings.CELERY_BROKER_URL) as connection:
        receiver = app.events.Receiver(connection, handlers={"*": on_event})
        with pytest.raises(_Seen):
            receiver.capture(limit=None, timeout=EVENTS_WAIT, wakeup=False)
    # The client's task-sent, the worker's received, started and succeeded.
    assert {"task-sent", "task-received", "task-started", "task-succeeded"} <= set(seen)
    assert seen["task-succeeded"] == {hostname}
    wait_for(
        lambda: _flower_state(flower, sent[0]) == "SUCCESS",
        timeout=30,
        what="Flower to list the task as succeeded",
    )

    url = f"http://127.0.0.1:{port}/metrics"
    counted = ("authros_celery_tasks_total", (("state", "SUCCESS"), ("task", PROBE_TASK)))
    # Counted by the pool process, served by the worker's main process.
    wait_for(lambda: _samples(url).get(counted, 0) >= 1, timeout=30, what="the task counted")
    samples = _samples(url)
    for source in ("database", "redis", "chain", "disk"):
        assert samples[("authros_metrics_source_up", (("source", source),))] == 1, source
    assert samples[("authros_operator_balance_wei", ())] > 0
    assert samples[("authros_operator_nonce", ())] >= 1  # the stack's deployment
    assert ("authros_operator_alerts_open", ()) in samples
    assert any(key[0] == "authros_disk_free_bytes" for key in samples)
    assert requests.get(f"http://127.0.0.1:{port}/", timeout=30).status_code == 404
