"""Issue 14 end to end: robots get their key by SM2, and a rotation loses nothing.

Real parts only: a ROS master, the agent process (`python -m ros_agent pair`, then the node),
the simulated robot, the portal under gunicorn for the robot, the same portal (live server,
same database) in Chromium for its owner, Celery workers and anvil.

1. Two robots ask to be paired; the owner types each one's code on the robots page, checks
   the fingerprint against what the robot printed, approves one and refuses the other. The
   refused one gets nothing; the approved one writes its config with no key copied by hand.
2. The paired agent records the simulated robot and uploads.
3. The robot loses the portal (its web server stops; the owner's browser still works) and spools.
   The owner rotates the key in the browser; the robot keeps spooling under the old key.
4. The portal is back: every envelope arrives, none is rejected, those sealed under the old key
   after the rotation were re-sealed by the agent under the new key it fetched (encrypted to
   its SM2 key), and every record is anchored and passes the integrity check.
"""

import json
import os
import select
import signal
import subprocess
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import requests
import yaml
from playwright.sync_api import Page, expect

from accounts.models import ChainState, Owner, Robot, RobotPairing
from accounts.services.owners import owner_create
from chainworker import services as chain_services
from ros_agent import sim
from sharing.models import Record
from sharing.verification.opening import record_open
from smcrypto import sm2, sm4
from tests.ros_agent import conftest as ros_fixtures
from tests.ros_agent.conftest import python_module, running, stop_process, wait_until
from tests.support.agent_output import agent_final_stats, spool_queued, spool_queued_now_gone
from tests.support.anchoring_checks import assert_anchored_exactly_once
from tests.support.harness import WorkerStack, wait_for
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import Screenshots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(600),
]

# A real ROS master on a free port, as the agent's own tests start it.
ros_master = ros_fixtures.ros_master
OWNER = "fleet-owner"
# Seconds of robot clock a retired key is still taken for: short, so that what the robot
# captures after the rotation is refused under the old key and must be re-sealed.
CLOCK_SKEW = "1"


@pytest.fixture
def robot_stack(tmp_path, settings):
    """anvil, two workers, beat, and gunicorn for the robot (stopped to take it offline)."""
    stack = WorkerStack(tmp_path, env_overrides={"KEY_ROTATION_CLOCK_SKEW": CLOCK_SKEW})
    try:
        stack.configure_test_process(settings)
        settings.KEY_ROTATION_CLOCK_SKEW = float(CLOCK_SKEW)
        chain_services._clients.clear()
        chain_services.contract_deploy()
        stack.start_worker("w0")
        stack.start_worker("w1")
        stack.start_beat()
        stack.start_web()
        yield stack
    finally:
        stack.stop()


class Pairing:
    """`python -m ros_agent pair --json` running; what it printed when it asked."""

    def __init__(self, portal: str, name: str, folder: Path, log: Path) -> None:
        self.folder = folder
        self.log = log
        self.process = subprocess.Popen(
            python_module(
                "ros_agent", "pair", "--portal", portal, "--name", name,
                "--dir", str(folder), "--json", "--timeout", "240",
            ),
            stdout=subprocess.PIPE,
            stderr=log.open("wb"),
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip
        self.requested = self._event("requested")

    def _event(self, name: str) -> dict:
        ready, _, _ = select.select([self.process.stdout], [], [], 60)
        line = self.process.stdout.readline() if ready else ""
        assert line, f"the pair command printed nothing:\n{self.log.read_text()}"
        event = json.loads(line)
        assert event["event"] == name, event
        return event

    def finish(self) -> tuple[int, str]:
        out, _ = self.process.communicate(timeout=120)
        return self.process.returncode, out


def answer_in_browser(page: Page, base: str, pairing: Pairing, *, approve: bool) -> None:
    page.goto(f"{base}/robots/")
    page.fill("#id_code", pairing.requested["code"].lower().replace("-", " "))
    page.click("#pairing-find")
    # The owner checks what the robot printed against what the portal received.
    expect(page.locator("#pairing-fingerprint")).to_have_text(pairing.requested["fingerprint"])
    page.click("#pairing-approve" if approve else "#pairing-refuse")
    page.wait_for_url("**/robots/")


def test_pair_in_the_browser_then_rotate_while_offline_and_lose_nothing(
    ros_master, robot_stack, live_server, browser, artifacts, tmp_path
):
    stack = robot_stack
    shot = Screenshots(artifacts)
    owner = owner_create(username=OWNER, password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    wait_for(
        lambda: Owner.objects.get(pk=owner.pk).chain_state == ChainState.CONFIRMED,
        timeout=90,
        what="the owner's registration on chain",
    )
    page = browser.new_page()
    base = live_server.url
    page.goto(f"{base}/login/")
    page.fill("#id_username", OWNER)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")

    # --- 1. pairing: one approved, one refused -----------------------------------------------
    robot_dir, intruder_dir = tmp_path / "robot", tmp_path / "intruder"
    good = Pairing(stack.web_url, "cart-1", robot_dir, tmp_path / "pair-good.log")
    bad = Pairing(stack.web_url, "cart-1", intruder_dir, tmp_path / "pair-bad.log")
    assert good.requested["code"] != bad.requested["code"]
    private_key = (robot_dir / "robot.sm2").read_text().strip()
    assert good.requested["fingerprint"] == sm2.fingerprint(
        sm2.public_key_from_private(private_key)
    )
    assert (robot_dir / "robot.sm2").stat().st_mode & 0o777 == 0o600

    answer_in_browser(page, base, bad, approve=False)
    shot(page, "pairing-refused")
    answer_in_browser(page, base, good, approve=True)
    expect(page.locator("[data-testid=robot-row]")).to_contain_text("cart-1")
    shot(page, "pairing-approved")

    code, out = bad.finish()
    assert code != 0
    assert "pairing_refused" in bad.log.read_text()
    assert not (intruder_dir / "robot.token").exists()
    assert not (intruder_dir / "agent.yaml").exists()
    assert RobotPairing.objects.get(state=RobotPairing.State.REFUSED).robot is None

    code, out = good.finish()
    assert code == 0, good.log.read_text()
    paired = json.loads(out.splitlines()[-1])
    assert paired["event"] == "paired"
    robot = Robot.objects.get(pk=paired["robot"])
    config_path = robot_dir / "agent.yaml"
    for name in ("agent.yaml", "robot.token", "owner-keys.json", "robot.sm2"):
        assert (robot_dir / name).stat().st_mode & 0o777 == 0o600, name
    assert not (robot_dir / "pairing.json").exists()
    assert Robot.objects.count() == 1
    config = yaml.safe_load(config_path.read_text())
    assert "key_file" not in config  # nothing copied by hand
    # Quick retries for the test; everything else is as the pair command wrote it.
    config.update(backoff_max=1.0, stats_interval=1.0, shutdown_flush=15.0, flush_interval=0.3)
    config_path.write_text(yaml.safe_dump(config))
    old_key_id = owner.keys.get(is_current=True).key_id

    # --- 2. the agent records and uploads --------------------------------------------------
    env = ros_master.env
    agent_log, spool = tmp_path / "agent.log", robot_dir / "spool"
    with running(
        python_module("ros_agent", "--config", str(config_path)), env=env, log=agent_log
    ) as agent:
        with running(python_module("ros_agent.sim"), env=env, log=tmp_path / "sim.log"):
            wait_until(lambda: _stored(robot) >= 20, 60, "the paired robot's first records")

            # --- 3. offline; the owner rotates the key meanwhile ---------------------------
            stack.stop_web()
            wait_until(
                lambda: len(spool_queued(spool)) >= 20, 60, "the agent spooling while offline"
            )
            page.goto(f"{base}/account/key/")
            expect(page.locator("#key-rotate-submit")).to_be_enabled()
            page.fill("#id_password", TEST_PASSWORD)
            page.click("#key-rotate-submit")
            page.wait_for_url("**/account/key/")
            shot(page, "key-rotated")
            new_key = owner.keys.get(is_current=True)
            assert new_key.key_id != old_key_id
            rotated_with = len(spool_queued(spool))
            time.sleep(float(CLOCK_SKEW) + 0.5)
            wait_until(
                lambda: len(spool_queued(spool)) >= rotated_with + 30,
                60,
                "the agent spooling under the old key after the rotation",
            )

            # --- 4. back online: everything arrives -----------------------------------------
            back_online = datetime.now(UTC)
            offline_sent = spool_queued_now_gone(spool)  # what was spooled while offline
            stack.start_web()
            logs = [agent_log, *sorted(stack.logs.glob("*.log"))]
            wait_until(
                offline_sent,
                180,
                "what the agent spooled offline delivered after the rotation",
                logs=logs,
            )
        # The simulator stopped: nothing new is captured, the rest is sent.
        wait_until(lambda: not spool_queued(spool), 120, "the spool draining", logs=logs)
        assert stop_process(agent, signal.SIGINT) == 0

    log = agent_log.read_text()
    assert "re-sealed" in log, log[-3000:]
    stats = agent_final_stats(agent_log)
    assert (stats["failed"], stats["dropped"], stats["queued"]) == (0, 0, 0), stats
    assert not [p for p in (spool / "rejected").iterdir() if p.suffix == ".env"]
    records = list(Record.objects.filter(robot=robot).order_by("seq"))
    assert stats["sent"] == stats["spooled"] == len(records)
    seqs = [record.seq for record in records]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    retired = owner.keys.get(key_id=old_key_id).retired_at
    under_old = [r for r in records if r.key_id == old_key_id]
    under_new = [r for r in records if r.key_id == new_key.key_id]
    assert len(under_old) + len(under_new) == len(records)
    assert under_old  # captured before the rotation: accepted as sealed
    assert all(r.captured_at <= retired + timedelta(seconds=float(CLOCK_SKEW)) for r in under_old)
    # The agent could fetch the new key only once the portal was back: what it captured before
    # and the portal holds under the new key was spooled under the old one and re-sealed.
    assert any(r.captured_at < back_online for r in under_new)

    wait_for(
        lambda: (
            Record.objects.filter(robot=robot, status=Record.Status.ANCHORED).count()
            == len(records)
        ),
        timeout=180,
        what=f"all {len(records)} records anchored",
        interval=0.5,
    )
    assert_anchored_exactly_once(chain_services.chain_client())
    for record in records:
        opened = record_open(record_id=record.id, viewer=owner)
        assert json.loads(opened.plaintext)["Topic"] in (sim.ODOM_TOPIC, sim.IMAGE_TOPIC)

    # Unpairing stops key delivery: the robot's token no longer fetches anything.
    page.goto(f"{base}/robots/")
    page.click("[data-testid=revoke-robot]")
    page.click("[data-testid=robot-revoke-confirm]")  # the confirmation page
    token = (robot_dir / "robot.token").read_text().strip()
    refused = requests.get(
        f"{stack.web_url}/api/v1/robot-key/",
        headers={"Authorization": f"Token {token}"},
        timeout=30,
    )
    assert (refused.status_code, refused.json()["error"]) == (401, "not_authenticated")


def _stored(robot: Robot) -> int:
    return Record.objects.filter(robot=robot).count()
