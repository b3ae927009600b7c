"""A robot on the network pairs with the portal as the README's quickstart says, over a real
link and not loopback: the portal listens on every address (`PORTAL_HOST=0.0.0.0`) with the
hosts `make run` allows for `PORTAL_PUBLIC_URL` (stack.run.Stack.environment), and the robot
runs `python -m ros_agent pair --portal PORTAL_PUBLIC_URL` in a network namespace of the
test's own, joined to this one by a veth pair, where the portal's loopback is not its loopback.
A Host the portal does not allow is refused there; the public URL's host pairs, and the robot
fetches its owner's key with the token it got, so its agent.yaml is ready to run.

Needs root and `ip netns` (CI and `make test` run as root); elsewhere it is skipped, saying so.
"""

import json
import os
import select
import shutil
import subprocess
import sys
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import yaml

from accounts.models import ChainState, Owner, Robot
from accounts.services.owners import owner_create
from accounts.services.pairing import robot_pairing_answer
from smcrypto import sm4
from stack.anvil import free_port
from stack.run import Stack, StackConfig
from tests.support.harness import wait_for
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = [
    pytest.mark.process,
    pytest.mark.worker,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(300),
]

EVERY_ADDRESS = "0.0.0.0"  # noqa: S104


@dataclass(frozen=True)
class RobotNetwork:
    namespace: str
    portal_address: str  # this namespace's end of the link
    stray_address: str  # on the link's network, but no host the portal allows

    def run(self, *command: str) -> list[str]:
        """The command as run on the robot: inside its network namespace."""
        return ["ip", "netns", "exec", self.namespace, *command]


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, check=check)


def _free_subnet() -> int:
    """A 10.77.N.0/24 that no interface of this namespace has yet (parallel runs pick apart)."""
    used = _ip("-4", "-o", "addr").stdout
    for _ in range(50):
        third = 100 + uuid.uuid4().int % 150
        if f" 10.77.{third}." not in used:
            return third
    pytest.fail("no free 10.77.N.0/24 for the robot's link")


@pytest.fixture
def robot_network() -> Iterator[RobotNetwork]:
    """A network namespace for the robot, with a veth link 10.77.N.2 (robot) <-> 10.77.N.1
    (here); both removed afterwards."""
    if shutil.which("ip") is None:
        pytest.skip("needs iproute2's `ip` (Debian: iproute2) for a network namespace")
    suffix = uuid.uuid4().hex[:8]
    namespace, here, there = f"authros-robot-{suffix}", f"arh{suffix}", f"arr{suffix}"
    added = _ip("netns", "add", namespace, check=False)
    if added.returncode != 0:
        pytest.skip(f"`ip netns add` is not permitted here ({added.stderr.strip()}): needs root")
    try:
        third = _free_subnet()
        _ip("link", "add", here, "type", "veth", "peer", "name", there, "netns", namespace)
        _ip("addr", "add", f"10.77.{third}.1/24", "dev", here)
        _ip("link", "set", here, "up")
        _ip("-n", namespace, "addr", "add", f"10.77.{third}.2/24", "dev", there)
        _ip("-n", namespace, "link", "set", there, "up")
        _ip("-n", namespace, "link", "set", "lo", "up")
        yield RobotNetwork(namespace, f"10.77.{third}.1", f"10.77.{third}.3")
    finally:
        _ip("link", "del", here, check=False)  # its peer goes with it
        _ip("netns", "del", namespace, check=False)


def _status_from_robot(network: RobotNetwork, url: str, host: str) -> str:
    """The HTTP status the robot gets for url with this Host header (curl, in its namespace)."""
    done = subprocess.run(
        network.run(
            "curl", "-s", "-o", "/dev/null", "-w", "%{http_code}", "--max-time", "20",
            "-H", f"Host: {host}", url,
        ),
        capture_output=True,
        text=True,
        check=False,
    )  # fmt: skip
    return done.stdout


def test_a_robot_in_its_own_network_pairs_at_the_public_url(
    robot_network, worker_stack, tmp_path, monkeypatch
):
    monkeypatch.delenv("DJANGO_ALLOWED_HOSTS", raising=False)
    stack = worker_stack(workers=1)
    port = free_port()
    public = f"http://{robot_network.portal_address}:{port}"
    make_run = Stack(
        StackConfig.from_environment(
            {
                "AUTHROS_VAR_DIR": str(tmp_path / "make-run"),
                "PORTAL_HOST": EVERY_ADDRESS,
                "PORTAL_PUBLIC_URL": public,
                "PORTAL_PORT": str(port),
            }
        )
    )
    allowed = make_run.environment()["DJANGO_ALLOWED_HOSTS"]
    stack.web_port = port
    stack.start_web(
        workers=1, host=EVERY_ADDRESS, env={**stack.env(), "DJANGO_ALLOWED_HOSTS": allowed}
    )
    owner = owner_create(username="yard-owner", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    wait_for(
        lambda: Owner.objects.get(pk=owner.pk).chain_state == ChainState.CONFIRMED,
        timeout=90,
        what="the owner's registration on chain",
    )

    # The robot reaches the portal over the link; a Host the portal does not allow is refused.
    api = f"{public}/api/"
    assert _status_from_robot(robot_network, api, f"{robot_network.portal_address}:{port}") == "404"
    assert _status_from_robot(robot_network, api, f"{robot_network.stray_address}:{port}") == "400"

    robot_dir, log = tmp_path / "robot", tmp_path / "pair.log"
    pair = subprocess.Popen(
        robot_network.run(
            sys.executable, "-m", "ros_agent", "pair", "--portal", public, "--name", "yard-1",
            "--dir", str(robot_dir), "--json", "--timeout", "120",
        ),
        stdout=subprocess.PIPE,
        stderr=log.open("wb"),
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    try:
        ready, _, _ = select.select([pair.stdout], [], [], 60)
        line = pair.stdout.readline() if ready else ""
        assert line, f"the pair command printed nothing:\n{log.read_text()}"
        requested = json.loads(line)
        assert requested["event"] == "requested", requested
        robot_pairing_answer(
            owner=owner, code=requested["code"], approve=True, actor=None, name=None
        )
        out, _ = pair.communicate(timeout=120)
    finally:
        if pair.poll() is None:
            pair.kill()
            pair.wait(timeout=10)
    assert pair.returncode == 0, log.read_text()
    paired = json.loads(out.splitlines()[-1])
    assert paired["event"] == "paired", paired
    robot = Robot.objects.get(pk=paired["robot"])
    assert (robot.owner_id, robot.name) == (owner.pk, "yard-1")
    config = yaml.safe_load((robot_dir / "agent.yaml").read_text())
    assert config["portal_url"] == public
    # fetched with the robot's token, over the link, after the approval
    assert json.loads((robot_dir / "owner-keys.json").read_text())
