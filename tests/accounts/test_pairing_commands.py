"""`make run`'s demo robot is paired as any robot is: `python -m ros_agent pair` against the
portal over HTTP, approved by `manage.py robot_pair_approve` (the owner's service, without a
browser), and `demo_setup` then knows the pairing holds."""

import json
import threading
from io import StringIO

import pytest
from django.core.management import CommandError, call_command

from accounts.models import Robot
from accounts.selectors import owner_by_username, owner_key_bytes, owner_key_current, robot_by_token
from ros_agent.config import load_config
from ros_agent.pairing import pair
from tests.ros_agent.conftest import wait_until

pytestmark = pytest.mark.django_db(transaction=True)


class Lines:
    """What the pair command prints, line by line, for another thread to read."""

    def __init__(self) -> None:
        self.text = ""

    def write(self, text: str) -> None:
        self.text += text

    def flush(self) -> None:
        pass

    def events(self) -> list[dict]:
        return [json.loads(line) for line in self.text.splitlines() if line.strip()]


def _demo_setup(folder, url) -> dict:
    out = StringIO()
    call_command("demo_setup", "--dir", str(folder), "--portal-url", url, stdout=out)
    return json.loads(out.getvalue())


def test_the_demo_robot_is_paired_by_sm2_and_approved_without_a_browser(
    deployed, live_server, tmp_path
):
    demo = _demo_setup(tmp_path / "demo", live_server.url)
    assert demo["robot_paired"] is False
    printed, result = Lines(), {}

    def run_pair() -> None:
        try:
            result["config"] = pair(
                portal_url=live_server.url,
                name="demo-robot",
                folder=tmp_path / "demo" / "robot",
                timeout=60,
                out=printed,
                machine=True,
                sleep=lambda _seconds: threading.Event().wait(0.2),
            )
        except Exception as exc:
            result["error"] = repr(exc)

    robot_side = threading.Thread(target=run_pair)
    robot_side.start()
    wait_until(lambda: printed.events(), 30, "the pairing code")
    code = printed.events()[0]["code"]
    with pytest.raises(CommandError, match="pairing_not_found"):
        call_command("robot_pair_approve", "--owner", "demo", "--code", "0000-0000")
    out = StringIO()
    call_command("robot_pair_approve", "--owner", "demo", "--code", code, stdout=out)
    approved = json.loads(out.getvalue())
    assert approved["fingerprint"] == printed.events()[0]["fingerprint"]
    robot_side.join(60)
    assert not robot_side.is_alive()
    assert "error" not in result, result
    with pytest.raises(CommandError, match="pairing_already_answered"):
        call_command("robot_pair_approve", "--owner", "demo", "--code", code)

    config = load_config(result["config"])
    owner = owner_by_username("demo")
    assert config.paired
    assert config.key == owner_key_bytes(owner_key_current(owner))
    robot = robot_by_token(config.token)
    assert str(robot.pk) == config.robot == approved["robot"]
    assert robot.public_key
    assert _demo_setup(tmp_path / "demo", live_server.url)["robot_paired"] is True
    assert Robot.objects.count() == 1
