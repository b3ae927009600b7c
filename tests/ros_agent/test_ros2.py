"""The agent on ROS 2: a real Cyclone DDS publisher (as rmw_cyclonedds publishes: rt/ topics,
pkg::msg::dds_::Type_ types) to the agent (`python -m ros_agent --ros2`, its own process) to
the real portal (live server, the session's anvil); every record is opened in the portal as its
owner and compared with the values that were published. DDS stays on this machine: the
project's loopback-only CYCLONEDDS_URI, set before any participant exists, and a DDS domain
of this run's own.
"""

import base64
import os
import re
import signal
import subprocess
import sys
from datetime import UTC, datetime
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from ros_agent import dds, ros2msg, sim
from ros_agent.sim2 import Ros2Publisher
from tests.ros_agent.conftest import (
    REPO_ROOT,
    published_odometry,
    python_module,
    running,
    stop_process,
    wait_until,
)
from tests.support.custom_msgs import (
    INSPECTION,
    INSPECTION_TOPIC,
    LEARNED,
    MSG_DIR,
    inspection,
    inspection_record,
)
from tests.support.portal_checks import opened_records, robot_config, stamp_time
from tests.support.recordings import (
    CHATTER,
    ODOM,
    TOPICS,
    comparable,
    expected_data,
    make_samples,
    ros2_store,
    ros2_type,
)

pytestmark = [
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(300),
]

PER_TOPIC = 3


def test_the_loopback_config_keeps_dds_on_this_machine(tmp_path):
    config = dds.write_loopback_config(tmp_path / "c.xml")
    env = dds.loopback_environment(config, domain_id=7)
    assert env == {"CYCLONEDDS_URI": config.as_uri(), "ROS_DOMAIN_ID": "7"}
    # What Cyclone DDS makes of it, from its own trace of a participant's start.
    trace = tmp_path / "cyclonedds.log"
    tracing = f"<Tracing><Verbosity>config</Verbosity><OutputFile>{trace}</OutputFile></Tracing>"
    started = subprocess.run(
        [sys.executable, "-c", "from cyclonedds.domain import DomainParticipant as P; P(7)"],
        env={**os.environ, "CYCLONEDDS_URI": f"{env['CYCLONEDDS_URI']},{tracing}"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert started.returncode == 0, started.stderr
    log = trace.read_text()
    assert re.search(r"selected interfaces: lo \(", log), log[-2000:]
    assert "Domain/General/AllowMulticast/#text: false" in log
    assert "Domain/Discovery/Peers/Peer[@Address]: 127.0.0.1" in log
    assert dds.dds_topic_name("/robot/odom") == "rt/robot/odom"
    assert dds.dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"


def test_a_ros2_publisher_reaches_the_portal_through_the_agent_with_every_value(
    live_server, make_robot, ros2_env, tmp_path
):
    domain, env = ros2_env
    setup = make_robot()
    config = robot_config(tmp_path / "robot", url=live_server.url, setup=setup)
    typestore = ros2_store()
    samples = make_samples(typestore, PER_TOPIC)
    publisher = Ros2Publisher(domain)
    for topic, ros_type in TOPICS:
        publisher.writer(topic, ros2_type(ros_type))
    started = datetime.now(UTC)

    agent_log = tmp_path / "agent.log"
    with running(
        python_module("ros_agent", "--ros2", "--config", str(config)), env=env, log=agent_log
    ) as agent:
        wait_until(
            lambda: (
                all(publisher.matched(topic) for topic, _ in TOPICS) or agent.poll() is not None
            ),
            60,
            "the agent's DDS readers",
        )
        assert agent.poll() is None, agent_log.read_text()
        for sample in samples:
            publisher.publish(sample.topic, sample.msg)
        stored = opened_records(setup.robot, expected=len(samples))
        assert stop_process(agent, signal.SIGINT) == 0
    log = agent_log.read_text()
    assert "Traceback" not in log
    assert "sent=24 spooled=24 failed=0 dropped=0 queued=0" in log

    by_key = {(s.topic, stamp_time(s.stamp_ns)): s for s in samples if s.has_header}
    chatter = {s.msg.data: s for s in samples if not s.has_header}
    for record, document in stored:
        if record.topic == CHATTER[0]:
            sample = chatter.pop(document["K"]["data"])
            assert started <= record.captured_at <= datetime.now(UTC)  # no stamp: when received
        else:
            sample = by_key.pop((record.topic, record.captured_at))
        assert (document["Topic"], document["Type"]) == (sample.topic, sample.ros_type)
        assert comparable(document["K"]) == expected_data(sample, ros1=False)
    assert not by_key
    assert not chatter


def test_the_simulated_ros2_robot_feeds_the_agent_the_papers_topics(
    live_server, make_robot, ros2_env, tmp_path
):
    _, env = ros2_env
    setup = make_robot()
    topics = [(sim.ODOM_TOPIC, "nav_msgs/Odometry"), (sim.IMAGE_TOPIC, "sensor_msgs/Image")]
    config = robot_config(tmp_path / "robot", url=live_server.url, setup=setup, topics=topics)
    sim_log = tmp_path / "sim2.log"
    with running(
        python_module("ros_agent", "--ros2", "--config", str(config)),
        env=env,
        log=tmp_path / "agent.log",
    ) as agent:
        with running(
            python_module("ros_agent.sim2", "--duration", "2", "--wait-for-subscriber", "60"),
            env=env,
            log=sim_log,
        ) as robot:
            assert robot.wait(90) == 0, sim_log.read_text()
        wait_until(
            lambda: len(list((tmp_path / "robot/spool/queue").glob("*.env"))) == 0,
            30,
            "the spool draining",
        )
        assert stop_process(agent, signal.SIGINT) == 0
    from sharing.models import Record

    count = Record.objects.filter(robot=setup.robot).count()
    assert count >= 15, (tmp_path / "agent.log").read_text()[-3000:]
    published = published_odometry(sim_log)
    kinds = set()
    for record, document in opened_records(setup.robot, expected=count):
        kinds.add(record.topic)
        data = document["K"]
        if record.topic == sim.ODOM_TOPIC:
            assert data == published(data)
        else:
            assert (data["width"], data["height"], data["encoding"]) == (320, 240, "bgr8")
            png = base64.b64decode(data["data"])
            pixels = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
            assert any(np.array_equal(pixels, sim.draw_scene(frame)) for frame in range(5))
    assert kinds == {sim.ODOM_TOPIC, sim.IMAGE_TOPIC}


def test_the_ros2_agent_refuses_a_type_it_does_not_know_with_a_clear_message(ros2_env, tmp_path):
    _, env = ros2_env
    robot = SimpleNamespace(
        key=bytes(16),
        token="t",
        robot=SimpleNamespace(id="7c9e6679-7425-40de-944b-e07fc1f90ae7"),
        owner=SimpleNamespace(user=SimpleNamespace(username="alice")),
    )
    topics = [CHATTER, ("/secret", "my_pkg/Secret")]
    config = robot_config(tmp_path, url="http://127.0.0.1:9", setup=robot, topics=topics)
    answer = subprocess.run(
        python_module("ros_agent", "--ros2", "--config", str(config)),
        env=env,
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert answer.returncode == 2
    assert (
        "topic /secret: unknown message type my_pkg/msg/Secret: no my_pkg/msg/Secret.msg in "
        "no folder (set msg_dirs)" in answer.stderr
    )
    assert "Traceback" not in answer.stderr


def test_a_best_effort_publisher_of_a_reliable_type_is_recorded_too(
    live_server, make_robot, ros2_env, tmp_path
):
    """Odometry is read reliably, which does not match a best-effort publisher: the agent sees
    the publisher's QoS and reads that topic best effort (as rosbag2 adapts)."""
    domain, env = ros2_env
    setup = make_robot()
    topics = [(sim.ODOM_TOPIC, "nav_msgs/Odometry")]
    config = robot_config(tmp_path / "robot", url=live_server.url, setup=setup, topics=topics)
    typestore = ros2_store()
    samples = [s for s in make_samples(typestore, 5) if (s.topic, s.ros_type) == ODOM]
    publisher = Ros2Publisher(domain)
    publisher.writer(ODOM[0], ros2_type(ODOM[1]), best_effort=True)
    agent_log = tmp_path / "agent.log"
    with running(
        python_module("ros_agent", "--ros2", "--config", str(config)), env=env, log=agent_log
    ) as agent:
        wait_until(lambda: publisher.matched(ODOM[0]), 60, "the agent's best-effort reader")
        for sample in samples:
            publisher.publish(sample.topic, sample.msg)
        stored = opened_records(setup.robot, expected=len(samples))
        assert stop_process(agent, signal.SIGINT) == 0
    assert (
        "/robot/odom has a best-effort publisher: reading it best effort" in agent_log.read_text()
    )
    by_stamp = {stamp_time(s.stamp_ns): s for s in samples}
    for record, document in stored:
        assert comparable(document["K"]) == expected_data(
            by_stamp.pop(record.captured_at), ros1=False
        )
    assert not by_stamp


def test_a_custom_nested_type_is_learned_from_msg_files_and_every_field_reaches_the_portal(
    live_server, make_robot, ros2_env, tmp_path
):
    """The robot publishes authros_test_msgs/Inspection (three levels of its own types), which
    no type store holds: the agent (Jazzy's store) learns it from the `.msg` folder its
    agent.yaml names, reads it over Cyclone DDS, and each record opens to every field."""
    domain, env = ros2_env
    setup = make_robot()
    config = robot_config(
        tmp_path / "robot",
        url=live_server.url,
        setup=setup,
        topics=[(INSPECTION_TOPIC, INSPECTION)],
        ros2_distro="jazzy",
        msg_dirs=[str(MSG_DIR)],
    )
    typestore = ros2msg.default_typestore("jazzy")
    ros2msg.learn_message_types(typestore, [ros2_type(INSPECTION)], [MSG_DIR])
    publisher = Ros2Publisher(domain, typestore)
    publisher.writer(INSPECTION_TOPIC, ros2_type(INSPECTION))
    agent_log = tmp_path / "agent.log"
    with running(
        python_module("ros_agent", "--ros2", "--config", str(config)), env=env, log=agent_log
    ) as agent:
        wait_until(
            lambda: publisher.matched(INSPECTION_TOPIC) or agent.poll() is not None,
            60,
            "the agent's DDS reader of the custom type",
        )
        assert agent.poll() is None, agent_log.read_text()
        for index in range(PER_TOPIC):
            publisher.publish(INSPECTION_TOPIC, inspection(typestore, index))
        stored = opened_records(setup.robot, expected=PER_TOPIC)
        assert stop_process(agent, signal.SIGINT) == 0
    log = agent_log.read_text()
    assert f"learned {', '.join(LEARNED)} from .msg files" in log
    assert "Traceback" not in log
    documents = sorted((document for _, document in stored), key=lambda d: d["K"]["round"])
    assert [document["Type"] for document in documents] == [INSPECTION] * PER_TOPIC
    assert [document["K"] for document in documents] == [
        inspection_record(index) for index in range(PER_TOPIC)
    ]
