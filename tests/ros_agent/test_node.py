"""The agent node end to end: a real ROS master, `rostopic pub`, the simulator, the agent in
subprocesses, and the in-test records endpoint checking and opening every envelope."""

import base64
import itertools
import math
import signal
import subprocess
import xmlrpc.client
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ros_agent import sim
from tests.ros_agent.conftest import (
    OWNER,
    REPO_ROOT,
    ROBOT,
    TOKEN,
    RosMaster,
    chatter_record,
    published_odometry,
    python_module,
    running,
    stop_process,
    wait_until,
    write_key_file,
)
from tests.support.agent_output import agent_final_stats, agent_stats, spool_queued
from tests.support.records_server import RecordsServer

pytestmark = pytest.mark.timeout(90)


def _subscribed(master: RosMaster, topic: str) -> bool:
    _, _, (_, subscribers, _) = xmlrpc.client.ServerProxy(master.uri).getSystemState("/pytest")
    return any(
        name == topic and any(node.startswith("/authros_agent") for node in nodes)
        for name, nodes in subscribers
    )


def _agent_yaml(
    folder: Path, portal: RecordsServer, key_file: Path, topics: list[tuple[str, str]], **extra
) -> Path:
    settings = {
        "portal_url": portal.url,
        "token": TOKEN,
        "robot": ROBOT,
        "owner": OWNER,
        "key_file": key_file.name,  # relative to the yaml
        "topics": [{"name": name, "type": ros_type} for name, ros_type in topics],
        **extra,
    }
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


@pytest.mark.process
def test_agent_refuses_a_key_file_that_others_can_read(tmp_path, owner_key, portal):
    key_file = write_key_file(tmp_path / "alice.sm4", owner_key, 0o644)
    config = _agent_yaml(tmp_path, portal, key_file, [("/chatter", "std_msgs/String")])
    result = subprocess.run(
        python_module("ros_agent", "--config", str(config)),
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert result.returncode == 2
    assert "has mode 0644" in result.stderr
    assert "chmod 600" in result.stderr


@pytest.mark.parametrize(
    ("params", "message"),
    [
        (["_topics:=[{name: /x, type: std_msgs/String}]"], "missing required setting(s): token"),
        (
            [f"_token:={TOKEN}", "_topics:=[{name: /x, type: foo_msgs/Bar}]"],
            "unknown message type foo_msgs/Bar",
        ),
    ],
)
def test_agent_started_with_bad_ros_parameters_says_why_and_exits(
    ros_master, portal, key_file, tmp_path, params, message
):
    common = [
        f"_portal_url:={portal.url}",
        f"_robot:={ROBOT}",
        f"_owner:={OWNER}",
        f"_key_file:={key_file}",
        f"_spool_dir:={tmp_path / 'spool'}",
    ]
    result = subprocess.run(
        python_module("ros_agent", *common, *params),
        cwd=REPO_ROOT,
        env=ros_master.env,
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert result.returncode == 2
    assert message in result.stdout + result.stderr


def test_rostopic_pub_reaches_the_portal_across_an_outage_and_an_agent_crash(
    ros_master, portal, key_file, tmp_path
):
    spool = tmp_path / "spool"
    agent = python_module(
        "ros_agent",
        f"_portal_url:={portal.url}",
        f"_token:={TOKEN}",
        f"_robot:={ROBOT}",
        f"_owner:={OWNER}",
        f"_key_file:={key_file}",
        "_topics:=[{name: /chatter, type: std_msgs/String}]",
        f"_spool_dir:={spool}",
        "_flush_interval:=0.2",
        "_backoff_max:=0.5",
        "_stats_interval:=0.5",
    )
    publisher = ["rostopic", "pub", "-r", "10", "/chatter", "std_msgs/String", "data: hello"]
    env, logs = ros_master.env, tmp_path
    portal.stop()  # the portal is down when the robot starts

    with running(publisher, env=env, log=logs / "rostopic.log"):
        with running(agent, env=env, log=logs / "agent1.log") as first:
            wait_until(lambda: len(spool_queued(spool)) >= 8, 30, "the agent spooling offline")
            first.send_signal(signal.SIGKILL)  # a crash: no flush, no clean shutdown
            first.wait(10)
        left_by_crash = [int(path.stem) for path in spool_queued(spool)]

        portal.start()
        with running(agent, env=env, log=logs / "agent2.log", stop_signal=signal.SIGTERM) as second:
            wait_until(
                lambda: len(portal.records) >= len(left_by_crash) + 10, 30, "delivery resuming"
            )
            assert stop_process(second, signal.SIGTERM) == 0

    stats = agent_final_stats(logs / "agent2.log")
    assert len(agent_stats(logs / "agent2.log")) >= 2  # periodic, and final
    assert stats["failed"] == stats["dropped"] == stats["queued"] == 0
    assert stats["sent"] == len(left_by_crash) + stats["spooled"] == len(portal.records)
    seqs = portal.seqs
    assert seqs[: len(left_by_crash)] == left_by_crash  # what the crashed agent spooled, first
    assert seqs == sorted(set(seqs))  # in order, each once, none reused after the restart
    for stored in portal.records:
        assert stored.record == chatter_record("hello", stored.header["time"])
        assert (stored.header["owner"], stored.header["robot"]) == (OWNER, ROBOT)


def test_the_simulated_robot_reaches_the_portal_with_the_odometry_and_images_it_published(
    ros_master, portal: RecordsServer, key_file, tmp_path
):
    topics = [(sim.ODOM_TOPIC, "nav_msgs/Odometry"), (sim.IMAGE_TOPIC, "sensor_msgs/Image")]
    config = _agent_yaml(
        tmp_path, portal, key_file, topics, spool_dir="spool", batch_size=20, flush_interval=0.3
    )
    env = ros_master.env
    agent_log = tmp_path / "agent.log"
    with running(
        python_module("ros_agent", "--config", str(config)), env=env, log=agent_log
    ) as agent:
        wait_until(
            lambda: (
                _subscribed(ros_master, sim.ODOM_TOPIC) and _subscribed(ros_master, sim.IMAGE_TOPIC)
            ),
            30,
            "the agent's subscriptions",
        )
        with running(
            python_module("ros_agent.sim", "--duration", "4"), env=env, log=tmp_path / "sim.log"
        ) as robot:
            assert robot.wait(30) == 0
        assert stop_process(agent, signal.SIGINT) == 0  # Ctrl-C flushes what is left

    stats = agent_final_stats(agent_log)
    assert stats["sent"] == stats["spooled"] == len(portal.records)
    assert stats["queued"] == stats["failed"] == 0
    assert portal.seqs == sorted(set(portal.seqs))
    for stored in portal.records:
        assert stored.record["Time"] == stored.header["time"]
        assert stored.record["Time"] == stored.record["K"]["header"]["stamp"]["iso"]
        assert stored.record["Type"] == stored.header["type"]
        assert stored.record["Topic"] == stored.header["topic"]
    odometry = [r.record["K"] for r in portal.records if r.header["type"] == "nav_msgs/Odometry"]
    images = [r.record["K"] for r in portal.records if r.header["type"] == "sensor_msgs/Image"]
    assert len(odometry) >= 25
    assert len(images) >= 2
    _check_odometry(odometry)
    # Equal to what was published, field by field, not only plausible.
    published = published_odometry(tmp_path / "sim.log")
    for pose in odometry:
        assert pose == published(pose)
    _check_images(images)


def _check_odometry(odometry: list[dict]) -> None:
    for pose in odometry:
        assert pose["header"]["frame_id"] == "odom"
        assert pose["child_frame_id"] == "base_link"
        p, q = pose["position"], pose["orientation"]
        assert abs(p["x"]) <= sim.HALF_WIDTH
        assert abs(p["y"]) <= sim.HALF_WIDTH / 2
        assert math.isclose(math.hypot(q["x"], q["y"], q["z"], q["w"]), 1.0, rel_tol=1e-9)
        assert 0 < pose["linear_velocity"]["x"] < 0.5
    neighbours = 0
    for before, after in itertools.pairwise(odometry):
        stamp_a, stamp_b = before["header"]["stamp"], after["header"]["stamp"]
        dt = (stamp_b["secs"] - stamp_a["secs"]) + (stamp_b["nsecs"] - stamp_a["nsecs"]) / 1e9
        # Stamps only have to increase: rospy.Rate catches up after a late tick, so two
        # messages can be much closer than 1/rate on a loaded machine.
        assert dt > 0
        if dt > 0.15:  # a message lost on a loaded machine: the chord is no tangent
            continue
        neighbours += 1
        dx = after["position"]["x"] - before["position"]["x"]
        dy = after["position"]["y"] - before["position"]["y"]
        speed = (before["linear_velocity"]["x"] + after["linear_velocity"]["x"]) / 2
        assert math.isclose(math.hypot(dx, dy) / dt, speed, rel_tol=0.05)
        q = before["orientation"]
        yaw = 2 * math.atan2(q["z"], q["w"])
        assert abs(math.remainder(math.atan2(dy, dx) - yaw, 2 * math.pi)) < 0.1
    assert neighbours >= 20


def _check_images(images: list[dict]) -> None:
    scenes = [sim.draw_scene(frame) for frame in range(10)]
    for image in images:
        assert (image["width"], image["height"], image["encoding"]) == (320, 240, "bgr8")
        png = base64.b64decode(image["data"])
        assert 50_000 < len(png) < 65_000
        pixels = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert pixels.shape == (240, 320, 3)
        assert any(np.array_equal(pixels, scene) for scene in scenes)
