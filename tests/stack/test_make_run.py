"""`make run` itself: `python -m stack run`, the command scripts/run.sh execs.

Started in a temporary work folder, on free ports, with a Redis key prefix and a Celery queue of
its own and the ROS side on a free master port. Once it prints its banner, the simulated
robot's data reaches the portal through the demo owner's agent; the owner logs in as a browser
does and reads an anchored record back, integrity-checked against the chain. DEBUG is off
(plain 404, static files still served). /healthz, /readyz and /metrics answer, and the logs are
readable lines with request ids. SIGINT then stops every process it started.
"""

import json
import os
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import psutil
import pytest
import requests
import yaml
from django.conf import settings

from stack.anvil import free_port
from stack.run import BANNER, STATE_FILE
from tests.support.harness import REPO_ROOT, wait_for

pytestmark = [
    pytest.mark.process,
    pytest.mark.worker,
    pytest.mark.nodb,  # it has a database of its own, in its work folder
    pytest.mark.timeout(300),
]

START_TIMEOUT = 180.0
STOP_TIMEOUT = 120.0
# Settings of the environment the suite runs in that would point `make run` elsewhere.
_NOT_INHERITED = (
    "CHAIN_RPC_URL",
    "DJANGO_DEBUG",
    "AUTHROS_SECRETS_DIR",
    "AUTHROS_MEDIA_ROOT",
    "CELERY_BROKER_URL",
    "CELERY_RESULT_BACKEND",
    "ROS_HOSTNAME",
    "ROS_NAMESPACE",
)


def _make_run_env(workdir: Path) -> dict[str, str]:
    env = {name: value for name, value in os.environ.items() if name not in _NOT_INHERITED}
    name = f"authros-make-run-{uuid.uuid4().hex[:12]}"
    return env | {
        "AUTHROS_VAR_DIR": str(workdir),
        "DATABASE_URL": f"sqlite:///{workdir / 'db.sqlite3'}",
        "PORTAL_HOST": "127.0.0.1",
        "PORTAL_PORT": str(free_port()),
        "ANVIL_PORT": str(free_port()),
        "REDIS_URL": settings.REDIS_URL,
        "REDIS_KEY_PREFIX": name,
        "CELERY_QUEUE": name,
        "ROS_MASTER_URI": f"http://127.0.0.1:{free_port()}/",
    }


def _output(path: Path) -> str:
    return path.read_text(errors="replace") if path.exists() else ""


def test_make_run_serves_the_robots_data_verified_and_stops_everything(tmp_path):
    workdir = tmp_path / "var"
    output = tmp_path / "make-run.out"
    with output.open("wb") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", "stack", "run"],
            cwd=REPO_ROOT,
            env=_make_run_env(workdir),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
    started: list[psutil.Process] = []
    try:

        def up() -> bool:
            if process.poll() is not None:
                raise AssertionError(f"make run exited:\n{_output(output)[-4000:]}")
            return BANNER in _output(output)

        wait_for(up, timeout=START_TIMEOUT, what="make run's banner", interval=0.5)
        state = json.loads((workdir / STATE_FILE).read_text())
        started = psutil.Process(process.pid).children(recursive=True)
        assert {"anvil", "worker", "verify", "beat", "web", "roscore", "sim", "agent"} <= set(
            state["processes"]
        )
        url = state["web_url"]
        username = state["demo"]["username"]
        password = (workdir / "demo" / "password").read_text().strip()
        assert f"{username} / {password}" in _output(output)
        # The demo robot was paired by SM2 (issue 14): no key file was copied to it.
        demo_config = yaml.safe_load(Path(state["demo"]["agent_config"]).read_text())
        assert "key_file" not in demo_config
        assert demo_config["sm2_key_file"] == "robot.sm2"
        assert not (workdir / "demo" / "sm4.key").exists()
        assert "pairing the demo robot" in _output(output)

        missing = requests.get(f"{url}/no-such-page/", timeout=10)
        assert missing.status_code == 404
        assert "DEBUG = True" not in missing.text  # Django's debug page says so
        assert "URLconf" not in missing.text
        static = requests.get(f"{url}/static/portal/portal.css", timeout=10)
        assert static.status_code == 200
        assert static.headers["Content-Type"].startswith("text/css")

        session = requests.Session()
        assert session.get(f"{url}/login/", timeout=10).status_code == 200
        signed_in = session.post(
            f"{url}/login/",
            data={
                "username": username,
                "password": password,
                "csrfmiddlewaretoken": session.cookies["csrftoken"],
            },
            timeout=30,
        )
        assert signed_in.status_code == 200, signed_in.text[-2000:]
        assert "sessionid" in session.cookies

        anchored: list[dict] = []

        def an_anchored_record() -> bool:
            answer = session.get(f"{url}/api/v1/records/?status=anchored", timeout=30)
            assert answer.status_code == 200, answer.text
            anchored[:] = answer.json()["results"]
            return bool(anchored)

        wait_for(an_anchored_record, timeout=90, what="a record of the robot anchored", interval=1)
        record = anchored[0]
        assert record["owner"] == username
        content: dict = {}

        def verified() -> bool:
            answer = session.get(f"{url}/api/v1/records/{record['id']}/content/", timeout=60)
            if answer.status_code != 200:
                return False
            content.update(answer.json())
            return True

        wait_for(verified, timeout=60, what="the record's content, checked", interval=1)
        assert content["verified"] is True
        assert _hex(content["digest"]) == _hex(record["digest"])

        # What a load balancer and a monitor ask (issue 36).
        assert requests.get(f"{url}/healthz", timeout=10).status_code == 200
        ready = requests.get(f"{url}/readyz", timeout=30)
        assert ready.status_code == 200, ready.text
        scraped = requests.get(f"{url}/metrics", timeout=30).text
        assert 'authros_uploads_total{result="stored"}' in scraped
        # counted by the verify worker, read through the web's /metrics
        assert 'authros_verdicts_total{outcome="verified"}' in scraped
        # make run's logs are readable lines, each request's with its id
        access = [
            line
            for line in (workdir / "log" / "web.log").read_text().splitlines()
            if " portal.access " in line
        ]
        assert access
        assert all(" request_id=" in line for line in access)
    finally:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
        try:
            code = process.wait(timeout=STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            code = process.wait()
            for child in started:
                child.kill()

    text = _output(output)
    assert code == 0, text[-4000:]
    assert "stopping what the stack started" in text
    left = [child for child in started if _alive(child)]
    assert not left, f"still running after make run stopped: {[c.cmdline() for c in left]}"
    assert (workdir / "anvil" / "state.json").exists()  # anvil wrote its state on the way out


def _hex(value: str) -> str:
    return value.lower().removeprefix("0x")


def _alive(process: psutil.Process) -> bool:
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False
