"""A paired robot signs every envelope it seals, on every path (DESIGN.md "Provenance"): the
rospy node, the ROS 2 agent, the import of recordings and the uploader's re-seal after a key
rotation; a robot set up by hand (token and key file) seals unsigned.

The in-test records endpoint stands in for the portal: told the paired robot's public key, it
refuses (400 `invalid_signature`) every envelope that does not carry this robot's valid
signature, and the tests check every stored envelope's signature again themselves.
"""

import signal
from datetime import UTC, datetime
from pathlib import Path

import genpy
import pytest
import yaml
from std_msgs.msg import String

from ros_agent import bags, sim
from ros_agent.config import load_config
from ros_agent.counters import AgentCounters
from ros_agent.keyring import Keyring
from ros_agent.pipeline import pipeline_build
from ros_agent.sealing import RobotSigningKey, robot_signing_key, seal_record
from ros_agent.spool import Spool
from ros_agent.uploader import Outcome, PortalClient, Uploader
from ros_agent.wrapping import Recorder, envelope_header
from smcrypto import envelope, provenance, sm2, sm4
from tests.ros_agent.conftest import (
    OWNER,
    ROBOT,
    TOKEN,
    python_module,
    running,
    stop_process,
    wait_until,
    write_key_file,
    write_paired_robot_files,
)
from tests.support.recordings import (
    TOPICS,
    make_samples,
    ros1_store,
    ros2_store,
    write_ros1_bag,
    write_ros2_bag,
)
from tests.support.records_server import RECORDS_PATH, RecordsServer

pytestmark = pytest.mark.timeout(120)

CAPTURED = datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC)
SIM_TOPICS = [(sim.ODOM_TOPIC, "nav_msgs/Odometry"), (sim.IMAGE_TOPIC, "sensor_msgs/Image")]


@pytest.fixture
def pairing_key(tmp_path, owner_key) -> RobotSigningKey:
    """The robot's pairing key pair, its files written in tmp_path as pairing leaves them."""
    return RobotSigningKey.of(write_paired_robot_files(tmp_path, owner_key))


@pytest.fixture
def signing_portal(owner_key, pairing_key):
    """The records endpoint of a paired robot: every envelope must carry its signature."""
    server = RecordsServer(
        token=TOKEN,
        key=owner_key,
        owner=OWNER,
        robot=ROBOT,
        robot_public_key=pairing_key.public_key,
    )
    server.start()
    yield server
    server.stop()


def _agent_yaml(
    folder: Path, portal: RecordsServer, topics: list[tuple[str, str]], *, paired: bool, **extra
) -> Path:
    keys = (
        {"sm2_key_file": "robot.sm2", "keys_file": "owner-keys.json"}
        if paired
        else {"key_file": "alice.sm4"}
    )
    settings = {
        "portal_url": portal.url,
        "token": TOKEN,
        "robot": ROBOT,
        "owner": OWNER,
        "topics": [{"name": name, "type": ros_type} for name, ros_type in topics],
        "spool_dir": "spool",
        **keys,
        **extra,
    }
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


def _assert_signed_by(portal: RecordsServer, key: RobotSigningKey, *, at_least: int) -> None:
    assert len(portal.records) >= at_least
    for stored in portal.records:
        info = envelope.read_header(stored.envelope)
        assert info.signer == provenance.key_hash(key.public_key)
        header, plaintext = envelope.open(portal.key, stored.envelope)
        provenance.signature_check(key.public_key, header, plaintext)


def _sim_messages() -> list[tuple[object, str, str]]:
    stamp = genpy.Time(1_763_733_600, 123_456_000)
    return [
        (sim.odometry_message(sim.figure_eight(0.5), stamp), *SIM_TOPICS[0]),
        (sim.image_message(sim.draw_scene(3), stamp), *SIM_TOPICS[1]),
        (String(data="wörld"), "/chatter", "std_msgs/String"),
    ]


# --- the one way to seal ----------------------------------------------------------------------


def test_seal_record_signs_with_the_robots_key_and_leaves_a_hand_robots_record_unsigned():
    key = sm4.generate_key()
    signing_key = RobotSigningKey.of(sm2.generate_keypair()[0])
    header = envelope_header(
        owner=OWNER,
        robot=ROBOT,
        topic="/chatter",
        ros_type="std_msgs/String",
        seq=7,
        captured_at=CAPTURED,
    )
    signed = seal_record(key, header, b"plaintext", signing_key)
    opened, plaintext = envelope.open(key, signed)
    assert {name: opened[name] for name in header} == header
    assert provenance.verify_header(signing_key.public_key, opened, plaintext)
    unsigned = envelope.read_header(seal_record(key, header, b"plaintext", None))
    assert (unsigned.signer, unsigned.sig) == (None, None)
    assert unsigned.header == header


def test_only_a_paired_robot_has_a_signing_key(tmp_path, owner_key, pairing_key, portal):
    write_key_file(tmp_path / "alice.sm4", owner_key)
    paired = load_config(_agent_yaml(tmp_path, portal, SIM_TOPICS, paired=True))
    by_hand = load_config(_agent_yaml(tmp_path, portal, SIM_TOPICS, paired=False))
    assert robot_signing_key(paired) == pairing_key
    assert robot_signing_key(by_hand) is None
    assert pairing_key.private_key not in repr(pairing_key)


# --- every path -------------------------------------------------------------------------------


def test_a_paired_robots_pipeline_signs_odometry_images_and_strings(
    tmp_path, pairing_key, signing_portal
):
    """The parts every agent is built from (ros_agent.pipeline): what the Recorder seals
    reaches the portal signed, each kind of message."""
    config = load_config(_agent_yaml(tmp_path, signing_portal, SIM_TOPICS, paired=True))
    pipeline = pipeline_build(config, backoff_max=0.1)
    try:
        for msg, topic, ros_type in _sim_messages():
            assert pipeline.recorder.record(msg, topic=topic, ros_type=ros_type) is not None
        assert pipeline.uploader.drain() is Outcome.EMPTY
    finally:
        pipeline.spool.close()
    assert pipeline.counters.failed == 0
    _assert_signed_by(signing_portal, pairing_key, at_least=3)
    assert {stored.header["type"] for stored in signing_portal.records} == {
        "nav_msgs/Odometry",
        "sensor_msgs/Image",
        "std_msgs/String",
    }


def test_a_robot_set_up_by_hand_uploads_unsigned_and_a_paired_robots_portal_refuses_that(
    tmp_path, owner_key, portal, signing_portal
):
    write_key_file(tmp_path / "alice.sm4", owner_key)
    for server in (portal, signing_portal):
        config = load_config(_agent_yaml(tmp_path, server, SIM_TOPICS, paired=False, batch_size=1))
        pipeline = pipeline_build(config, backoff_max=0.1)
        try:
            pipeline.recorder.record(String(data="x"), topic="/chatter", ros_type="std_msgs/String")
            pipeline.uploader.drain()
        finally:
            pipeline.spool.close()
    (stored,) = portal.records
    info = envelope.read_header(stored.envelope)
    assert (info.signer, info.sig) == (None, None)
    assert signing_portal.records == []
    assert [upload.status for upload in signing_portal.uploads] == [400]
    (rejected,) = (tmp_path / "spool" / "rejected").glob("*.json")
    assert "invalid_signature" in rejected.read_text()


def test_the_ros2_agent_seals_signed(tmp_path, owner_key, pairing_key, portal):
    """It takes the pipeline as it is built; its DDS readers are tested running below, and so
    is the rospy node (importing rospy here would leave its atexit hook logging into pytest's
    closed streams)."""
    from ros_agent.ros2 import Ros2Agent

    agent = Ros2Agent(load_config(_agent_yaml(tmp_path, portal, SIM_TOPICS, paired=True)))
    try:
        agent.recorder.record(String(data="x"), topic="/chatter", ros_type="std_msgs/String")
        (item,) = agent.spool.peek(10)
    finally:
        agent.spool.close()
    header, plaintext = envelope.open(owner_key, item.envelope)
    assert provenance.verify_header(pairing_key.public_key, header, plaintext)


def test_an_imported_recording_is_signed(tmp_path, pairing_key, signing_portal, capsys):
    topics = list(TOPICS)
    config = _agent_yaml(tmp_path, signing_portal, topics, paired=True)
    ts1, ts2 = ros1_store(), ros2_store()
    files = [
        write_ros1_bag(tmp_path / "drive.bag", make_samples(ts1, 2), ts1),
        write_ros2_bag(
            tmp_path / "drive_mcap", make_samples(ts2, 2, base_ns=2 * 10**18), ts2, mcap=True
        ),
    ]
    code = bags.main(
        ["--config", str(config), "--no-progress", "--upload-timeout", "60", *map(str, files)]
    )
    output = "".join(capsys.readouterr())
    assert code == 0, output
    total = 2 * 2 * len(TOPICS)
    assert f"uploaded {total}, refused by the portal 0, waiting in the spool 0" in output
    _assert_signed_by(signing_portal, pairing_key, at_least=total)


def test_envelopes_resealed_after_a_rotation_are_signed_again(
    tmp_path, owner_key, pairing_key, signing_portal
):
    """The owner rotated its key while the robot was offline: the uploader re-seals what it
    spooled under the new key, signed, including an envelope spooled unsigned before the robot
    was paired; the portal refuses none of them."""
    new_key = sm4.generate_key()
    keyring = Keyring.of_one(owner_key)
    spool = Spool(tmp_path / "spool", max_bytes=10**7)
    counters = AgentCounters()
    uploader = Uploader(
        spool=spool,
        client=PortalClient(records_url=signing_portal.url + RECORDS_PATH, token=TOKEN, timeout=5),
        counters=counters,
        batch_size=4,
        backoff_base=0.01,
        backoff_max=0.05,
        keyring=keyring,
        key_updater=lambda: keyring.add(new_key) or True,
        signing_key=pairing_key,
    )
    recorder = Recorder(
        spool=spool,
        keyring=keyring,
        owner=OWNER,
        robot=ROBOT,
        counters=counters,
        signing_key=pairing_key,
    )
    try:
        header = envelope_header(
            owner=OWNER,
            robot=ROBOT,
            topic="/chatter",
            ros_type="std_msgs/String",
            seq=0,
            captured_at=CAPTURED,
        )
        spool.append(lambda seq: seal_record(owner_key, {**header, "seq": seq}, b'{"K":{}}', None))
        for index in range(5):
            recorder.record(String(data=f"m{index}"), topic="/chatter", ros_type="std_msgs/String")
        signed_before = {
            item.seq: envelope.read_header(item.envelope).sig for item in spool.peek(9)
        }
        signing_portal.key = new_key  # the rotation
        assert uploader.drain() is Outcome.EMPTY
    finally:
        spool.close()
    assert counters.failed == 0
    assert len(signing_portal.records) == 6
    assert {stored.envelope[4:12] for stored in signing_portal.records} == {
        envelope.key_id(new_key)
    }
    _assert_signed_by(signing_portal, pairing_key, at_least=6)
    assert signed_before[min(signed_before)] is None  # the one spooled before the pairing


# --- the agents running -----------------------------------------------------------------------


@pytest.mark.process
def test_the_ros1_node_signs_what_the_simulated_robot_publishes(
    ros_master, tmp_path, pairing_key, signing_portal
):
    config = _agent_yaml(
        tmp_path, signing_portal, SIM_TOPICS, paired=True, batch_size=20, flush_interval=0.3
    )
    with running(
        python_module("ros_agent", "--config", str(config)),
        env=ros_master.env,
        log=tmp_path / "agent.log",
    ) as agent:
        # logged once every topic is subscribed
        wait_until(lambda: "uploads to" in (tmp_path / "agent.log").read_text(), 30, "the agent")
        with running(
            python_module("ros_agent.sim", "--duration", "3"),
            env=ros_master.env,
            log=tmp_path / "sim.log",
        ) as robot:
            assert robot.wait(60) == 0, (tmp_path / "sim.log").read_text()[-2000:]
        assert stop_process(agent, signal.SIGINT) == 0  # Ctrl-C flushes what is left
    log = (tmp_path / "agent.log").read_text()
    assert "Traceback" not in log
    assert not list((tmp_path / "spool" / "rejected").glob("*")), log[-3000:]
    _assert_signed_by(signing_portal, pairing_key, at_least=10)
    assert {stored.header["topic"] for stored in signing_portal.records} == {
        sim.ODOM_TOPIC,
        sim.IMAGE_TOPIC,
    }


@pytest.mark.process
def test_the_ros2_agent_signs_what_the_simulated_ros2_robot_publishes(
    ros2_env, tmp_path, pairing_key, signing_portal
):
    _, env = ros2_env
    config = _agent_yaml(
        tmp_path, signing_portal, SIM_TOPICS, paired=True, batch_size=20, flush_interval=0.3
    )
    with running(
        python_module("ros_agent", "--ros2", "--config", str(config)),
        env=env,
        log=tmp_path / "agent.log",
    ) as agent:
        with running(
            python_module("ros_agent.sim2", "--duration", "2", "--wait-for-subscriber", "60"),
            env=env,
            log=tmp_path / "sim2.log",
        ) as robot:
            assert robot.wait(90) == 0, (tmp_path / "sim2.log").read_text()[-2000:]
        wait_until(lambda: len(signing_portal.records) >= 10, 30, "the records to arrive")
        assert stop_process(agent, signal.SIGINT) == 0
    log = (tmp_path / "agent.log").read_text()
    assert "Traceback" not in log
    assert not list((tmp_path / "spool" / "rejected").glob("*")), log[-3000:]
    _assert_signed_by(signing_portal, pairing_key, at_least=10)
