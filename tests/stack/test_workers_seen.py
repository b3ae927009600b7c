"""Celery workers started as `make run` starts them (stack/processes.py `celery_worker`) are
seen alive by monitoring: they answer `celery -A portal inspect ping`, and send the heartbeats
by which Flower tells a live worker from a dead one."""

import json
import socket
import subprocess
import uuid

import pytest
from kombu import Connection

from portal.celery import app
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
