"""The agent against the real portal: a ROS master, gunicorn, a Celery worker and beat, anvil.

Messages published by `rostopic pub` and by the simulated robot reach the portal, are anchored
on chain, and open (through the worker's integrity check) to exactly what was published. Then
the portal goes down for a while: the agent spools, and when the portal is back everything
arrives exactly once, in order, without a gap, and is anchored. Forged nodes listening on
the robot's topic (no key, a wrong key, a stale sequence number, another robot's token) are
refused and nothing of theirs is stored.
"""

import base64
import contextlib
import json
import signal
import uuid
import xmlrpc.client
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import requests
import yaml

from accounts.models import ChainState, Owner
from accounts.services.owners import owner_create
from accounts.services.robots import robot_create
from chainworker import services as chain_services
from ros_agent import sim
from sharing.models import Record
from sharing.verification.opening import record_open
from smcrypto import sm4
from tests.ros_agent.conftest import (
    OWNER,
    RosMaster,
    chatter_record,
    published_odometry,
    python_module,
    running,
    stop_process,
    wait_until,
)
from tests.support.agent_output import agent_final_stats, spool_queued, spool_queued_now_gone
from tests.support.anchoring_checks import assert_anchored_exactly_once
from tests.support.harness import WorkerStack, wait_for
from tests.support.portal_checks import robot_config
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(300),
]

CHATTER = "/chatter"


@pytest.fixture
def stack(tmp_path, settings):
    stack = WorkerStack(tmp_path)
    stack.configure_test_process(settings)
    chain_services._clients.clear()
    chain_services.contract_deploy()
    stack.start_worker("w0")
    stack.start_beat()
    stack.start_web()
    yield stack
    stack.stop()


def _agent_config(folder: Path, stack: WorkerStack) -> Path:
    """An owner and robot made through the services, and the agent's yaml for them.

    The owner's key is in `owner.sm4` and the robot's token in `robot.token`, in `folder`.
    """
    key = sm4.generate_key()
    owner = owner_create(username=OWNER, password=TEST_PASSWORD, sm4_key=key)
    robot, token = robot_create(owner=owner, name=f"sim-{uuid.uuid4().hex[:6]}")
    wait_for(
        lambda: type(owner).objects.get(pk=owner.pk).chain_state == ChainState.CONFIRMED,
        timeout=60,
        what="the owner's registration on chain by the worker",
    )
    topics = [
        (CHATTER, "std_msgs/String"),
        (sim.ODOM_TOPIC, "nav_msgs/Odometry"),
        (sim.IMAGE_TOPIC, "sensor_msgs/Image"),
    ]
    setup = RobotSetup(owner, key, robot, token)
    return robot_config(folder, url=stack.web_url, setup=setup, topics=topics)


def _subscribed(master: RosMaster, *topics: str) -> bool:
    _, _, (_, subscribers, _) = xmlrpc.client.ServerProxy(master.uri).getSystemState("/pytest")
    ours = {
        name for name, nodes in subscribers if any(n.startswith("/authros_agent") for n in nodes)
    }
    return set(topics) <= ours


def _stored(topic: str | None = None) -> int:
    records = Record.objects.all()
    return (records.filter(topic=topic) if topic else records).count()


def test_the_agent_delivers_to_the_real_portal_exactly_once_across_an_outage(
    ros_master, stack, tmp_path
):
    config = _agent_config(tmp_path, stack)
    spool = tmp_path / "spool"
    env, agent_log = ros_master.env, tmp_path / "agent.log"
    publisher = ["rostopic", "pub", "-r", "5", CHATTER, "std_msgs/String", "data: hello"]

    with running(
        python_module("ros_agent", "--config", str(config)), env=env, log=agent_log
    ) as agent:
        wait_until(
            lambda: _subscribed(ros_master, CHATTER, sim.ODOM_TOPIC, sim.IMAGE_TOPIC),
            30,
            "the agent's subscriptions",
        )
        with running(publisher, env=env, log=tmp_path / "rostopic.log"):
            with running(
                python_module("ros_agent.sim", "--duration", "3"), env=env, log=tmp_path / "sim.log"
            ) as robot:
                assert robot.wait(60) == 0
            wait_until(lambda: _stored(CHATTER) >= 5, 30, "chatter reaching the portal")
            wait_until(
                spool_queued_now_gone(spool),  # chatter goes on at 5 Hz meanwhile
                30,
                "the simulator's data reaching the portal",
            )

            stack.stop_web()  # the portal goes down; the robot keeps publishing
            before_outage = _stored()
            wait_until(
                lambda: len(spool_queued(spool)) >= 25, 30, "the agent spooling while offline"
            )
            assert _stored() == before_outage
            offline_sent = spool_queued_now_gone(spool)
            stack.start_web()
            wait_until(
                offline_sent,
                60,
                "what was spooled offline draining to the portal",
            )
            wait_until(lambda: _stored() >= before_outage + 25, 30, "delivery after the outage")
        assert stop_process(agent, signal.SIGINT) == 0  # Ctrl-C flushes what is left

    assert "could not deliver" in agent_log.read_text()  # it did notice the outage
    stats = agent_final_stats(agent_log)
    assert (stats["failed"], stats["dropped"], stats["queued"]) == (0, 0, 0), stats
    records = list(Record.objects.order_by("seq"))
    seqs = [record.seq for record in records]
    # Exactly once: every envelope the agent made is stored once, with no gap and no repeat.
    assert stats["sent"] == stats["spooled"] == len(records)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))

    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == len(records),
        timeout=90,
        what=f"all {len(records)} records anchored",
        interval=0.5,
    )
    assert_anchored_exactly_once(chain_services.chain_client())

    owner = records[0].owner
    published = published_odometry(tmp_path / "sim.log")
    kinds = Counter()
    for record in records:
        opened = record_open(record_id=record.id, viewer=owner)
        content = json.loads(opened.plaintext)
        assert content["Topic"] == opened.header["topic"] == record.topic
        assert content["Type"] == opened.header["type"] == record.data_type
        kinds[record.topic] += 1
        if record.topic == CHATTER:
            assert content == chatter_record("hello", opened.header["time"])
        elif record.topic == sim.IMAGE_TOPIC:
            _check_image(content["K"])
        else:
            assert content["K"] == published(content["K"])
    assert kinds[sim.ODOM_TOPIC] >= 20
    assert kinds[sim.IMAGE_TOPIC] >= 2
    assert kinds[CHATTER] >= 20

    # A body above the limit gets the API's JSON 413 through gunicorn too, and changes nothing.
    token = (tmp_path / "robot.token").read_text()
    oversized = requests.post(
        f"{stack.web_url}/api/v1/records/",
        data=b'{"envelope": "' + b"A" * (13 * 1024 * 1024) + b'"}',
        headers={"Authorization": f"Token {token}", "Content-Type": "application/json"},
        timeout=60,
    )
    assert (oversized.status_code, oversized.json()["error"]) == (413, "request_too_large")
    assert Record.objects.count() == len(records)


def _check_image(image: dict) -> None:
    assert (image["width"], image["height"], image["encoding"]) == (320, 240, "bgr8")
    pixels = cv2.imdecode(np.frombuffer(base64.b64decode(image["data"]), np.uint8), -1)
    assert any(np.array_equal(pixels, sim.draw_scene(frame)) for frame in range(10))


FORGERIES = {
    # mode of tests/ros_agent/forged_node.py: (status, error) the portal must answer
    "no_key": (400, "invalid_envelope"),
    "wrong_key": (403, "unknown_key"),
    "stale_seq": (409, "sequence_conflict"),
    "other_token": (403, "header_mismatch"),
}


def test_forged_nodes_on_the_robots_topic_are_refused_and_nothing_of_theirs_is_stored(
    ros_master, stack, tmp_path
):
    config = _agent_config(tmp_path, stack)
    settings = yaml.safe_load(config.read_text())
    owner = Owner.objects.get(user__username=OWNER)
    sibling, sibling_token = robot_create(owner=owner, name="sibling")
    victim_token = (tmp_path / "robot.token").read_text()
    env, agent_log = ros_master.env, tmp_path / "agent.log"
    publisher = ["rostopic", "pub", "-r", "5", CHATTER, "std_msgs/String", "data: hello"]

    with contextlib.ExitStack() as nodes:
        agent = nodes.enter_context(
            running(python_module("ros_agent", "--config", str(config)), env=env, log=agent_log)
        )
        nodes.enter_context(running(publisher, env=env, log=tmp_path / "rostopic.log"))
        wait_until(lambda: _stored(CHATTER) >= 3, 60, "the robot's own data reaching the portal")
        for mode in FORGERIES:
            forged = python_module(
                "tests.ros_agent.forged_node",
                f"--mode={mode}",
                f"--portal={stack.web_url}",
                f"--token={sibling_token if mode == 'other_token' else victim_token}",
                f"--owner={OWNER}",
                f"--robot={settings['robot']}",
                f"--topic={CHATTER}",
                f"--answers={tmp_path / mode}.jsonl",
                *(
                    []
                    if mode in ("no_key", "wrong_key")
                    else [f"--key-file={tmp_path / 'owner.sm4'}"]
                ),
            )
            nodes.enter_context(running(forged, env=env, log=tmp_path / f"{mode}.log"))
        wait_until(
            lambda: all(len(_answers(tmp_path / f"{mode}.jsonl")) >= 5 for mode in FORGERIES),
            60,
            "every forged node hearing the topic and uploading",
        )
        assert stop_process(agent, signal.SIGINT) == 0

    for mode, expected in FORGERIES.items():
        answers = _answers(tmp_path / f"{mode}.jsonl")
        assert {(a["status"], a["error"]) for a in answers} == {expected}, (mode, answers)
    # What is stored is exactly what the robot's own agent sent: the forgers added nothing.
    stats = agent_final_stats(agent_log)
    assert (stats["failed"], stats["dropped"], stats["queued"]) == (0, 0, 0), stats
    records = list(Record.objects.order_by("seq"))
    assert len(records) == stats["sent"]
    assert {record.robot_id for record in records} == {uuid.UUID(settings["robot"])}
    assert not sibling.records.exists()
    for record in records[:3]:
        opened = record_open(record_id=record.id, viewer=owner)
        assert json.loads(opened.plaintext) == chatter_record("hello", opened.header["time"])


def _answers(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
