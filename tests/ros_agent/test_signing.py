"""A paired robot signs every upload batch once (provenance v2, DESIGN.md "Provenance v2"),
on every path: the rospy node, the ROS 2 agent, the import of recordings, and across the
uploader's re-seal after a key rotation, which keeps each batch's signature and topic_seq.
What it captures waits in the spool sealed and unsigned. A robot set up by hand (token and
key file) sends unsigned records, without topic_seq.

The in-test records endpoint stands in for the portal: told the paired robot's public key, it
refuses (400 `invalid_signature`) every envelope that does not carry this robot's valid
signature, and the tests check every stored envelope's signature and numbering again
themselves (conftest.assert_batch_signed). Crashes, outages and restarts: test_batches.py.
"""

import signal
from datetime import UTC, datetime

import genpy
import pytest
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
    agent_yaml,
    assert_batch_signed,
    python_module,
    running,
    stop_process,
    wait_until,
    write_key_file,
)
from tests.support.recordings import (
    TOPICS,
    make_samples,
    ros1_store,
    ros2_store,
    write_ros1_bag,
    write_ros2_bag,
)
from tests.support.records_server import RECORDS_PATH

pytestmark = pytest.mark.timeout(120)

CAPTURED = datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC)
SIM_TOPICS = [(sim.ODOM_TOPIC, "nav_msgs/Odometry"), (sim.IMAGE_TOPIC, "sensor_msgs/Image")]


def _sim_messages() -> list[tuple[object, str, str]]:
    stamp = genpy.Time(1_763_733_600, 123_456_000)
    return [
        (sim.odometry_message(sim.figure_eight(0.5), stamp), *SIM_TOPICS[0]),
        (sim.image_message(sim.draw_scene(3), stamp), *SIM_TOPICS[1]),
        (String(data="wörld"), "/chatter", "std_msgs/String"),
    ]


# --- the one way to seal ----------------------------------------------------------------------


def test_seal_record_signs_one_record_on_its_own_as_v1_or_leaves_it_unsigned():
    """v1, what paired agents sent before v2 (the portal keeps verifying it)."""
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
    assert envelope.provenance_format(opened) == "v1"
    unsigned = envelope.read_header(seal_record(key, header, b"plaintext", None))
    assert (unsigned.signer, unsigned.sig) == (None, None)
    assert unsigned.header == header


def test_only_a_paired_robot_has_a_signing_key(tmp_path, owner_key, pairing_key, portal):
    write_key_file(tmp_path / "alice.sm4", owner_key)
    paired = load_config(agent_yaml(tmp_path, portal, SIM_TOPICS, paired=True))
    by_hand = load_config(agent_yaml(tmp_path, portal, SIM_TOPICS, paired=False))
    assert robot_signing_key(paired) == pairing_key
    assert robot_signing_key(by_hand) is None
    assert pairing_key.private_key not in repr(pairing_key)


# --- every path -------------------------------------------------------------------------------


def test_a_paired_robots_pipeline_signs_odometry_images_and_strings(
    tmp_path, pairing_key, signing_portal
):
    """The parts every agent is built from (ros_agent.pipeline): what the Recorder seals waits
    in the spool unsigned, and reaches the portal signed once as one batch, each kind of
    message, each topic counted from 0."""
    config = load_config(agent_yaml(tmp_path, signing_portal, SIM_TOPICS, paired=True))
    pipeline = pipeline_build(config, backoff_max=0.1)
    try:
        for msg, topic, ros_type in _sim_messages():
            assert pipeline.recorder.record(msg, topic=topic, ros_type=ros_type) is not None
        spooled = [envelope.read_header(item.envelope) for item in pipeline.spool.peek(10)]
        assert {info.provenance for info in spooled} == {"unsigned"}
        assert not any("topic_seq" in info.header for info in spooled)
        assert pipeline.uploader.drain() is Outcome.EMPTY
    finally:
        pipeline.spool.close()
    assert pipeline.counters.failed == 0
    assert assert_batch_signed(signing_portal, pairing_key, at_least=3) == {
        sim.ODOM_TOPIC: [0],
        sim.IMAGE_TOPIC: [0],
        "/chatter": [0],
    }
    assert len(signing_portal.uploads) == 1
    assert {stored.header["sig_size"] for stored in signing_portal.records} == {3}
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
        config = load_config(agent_yaml(tmp_path, server, SIM_TOPICS, paired=False, batch_size=1))
        pipeline = pipeline_build(config, backoff_max=0.1)
        try:
            pipeline.recorder.record(String(data="x"), topic="/chatter", ros_type="std_msgs/String")
            pipeline.uploader.drain()
        finally:
            pipeline.spool.close()
    (stored,) = portal.records
    info = envelope.read_header(stored.envelope)
    assert (info.signer, info.sig, info.provenance) == (None, None, "unsigned")
    assert "topic_seq" not in info.header
    assert not (tmp_path / "spool" / "topic_seq").exists()
    assert signing_portal.records == []
    assert [upload.status for upload in signing_portal.uploads] == [400]
    (rejected,) = (tmp_path / "spool" / "rejected").glob("*.json")
    assert "invalid_signature" in rejected.read_text()


def test_the_ros2_agent_signs_its_batches(tmp_path, owner_key, pairing_key, signing_portal):
    """It takes the pipeline as it is built; its DDS readers are tested running below, and so
    is the rospy node (importing rospy here would leave its atexit hook logging into pytest's
    closed streams)."""
    from ros_agent.ros2 import Ros2Agent

    config = agent_yaml(tmp_path, signing_portal, SIM_TOPICS, paired=True)
    agent = Ros2Agent(load_config(config))
    try:
        for text in ("x", "y"):
            agent.recorder.record(String(data=text), topic="/chatter", ros_type="std_msgs/String")
        assert {envelope.read_header(i.envelope).sig for i in agent.spool.peek(10)} == {None}
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()
    assert assert_batch_signed(signing_portal, pairing_key, at_least=2) == {"/chatter": [0, 1]}


def test_an_imported_recording_is_signed_and_counted_on_the_robots_counters(
    tmp_path, pairing_key, signing_portal, capsys
):
    """Imports go through the same spool and uploader: numbered on from what the robot
    counted before, in the one counters file of its spool."""
    topics = list(TOPICS)
    config = agent_yaml(tmp_path, signing_portal, topics, paired=True)
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
    streams = assert_batch_signed(signing_portal, pairing_key, at_least=total)
    assert streams == {topic: [0, 1, 2, 3] for topic, _ in TOPICS}

    # the live agent of the same robot, later, numbers on
    pipeline = pipeline_build(load_config(config), backoff_max=0.1)
    try:
        pipeline.recorder.record(String(data="live"), topic="/chatter", ros_type="std_msgs/String")
        assert pipeline.uploader.drain() is Outcome.EMPTY
    finally:
        pipeline.spool.close()
    assert assert_batch_signed(signing_portal, pairing_key)["/chatter"] == [0, 1, 2, 3, 4]


def test_a_rotation_reseals_under_the_new_key_keeping_each_batchs_signature_and_topic_seq(
    tmp_path, owner_key, pairing_key, signing_portal
):
    """The owner rotated its key while the robot was offline: each batch, signed under the
    old key as it leaves, is refused (403 unknown_key) and re-sealed under the new key with
    its header as it was signed (the v2 signature does not cover the key id); the next batch
    stays unsigned in the spool until it is signed in turn. The portal refuses none of them."""
    new_key = sm4.generate_key()
    keyring = Keyring.of_one(owner_key)
    spool = Spool(tmp_path / "spool", max_bytes=10**7)
    writes: list[tuple[int, bytes]] = []  # every envelope written in place of a queued one
    replace = spool.replace

    def replace_noting(seq: int, data: bytes) -> None:
        writes.append((seq, data))
        replace(seq, data)

    spool.replace = replace_noting
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
    recorder = Recorder(spool=spool, keyring=keyring, owner=OWNER, robot=ROBOT, counters=counters)
    try:
        seqs = [
            recorder.record(String(data=f"m{index}"), topic="/chatter", ros_type="std_msgs/String")
            for index in range(6)
        ]
        signing_portal.key = new_key  # the rotation
        assert uploader.drain() is Outcome.EMPTY
    finally:
        spool.close()
    assert counters.failed == 0
    assert assert_batch_signed(signing_portal, pairing_key, at_least=6) == {
        "/chatter": [0, 1, 2, 3, 4, 5]
    }
    assert {stored.envelope[4:12] for stored in signing_portal.records} == {
        envelope.key_id(new_key)
    }
    first, second = seqs[:4], seqs[4:]
    old, new = envelope.key_id(owner_key), envelope.key_id(new_key)
    # signed under the old key, re-sealed under the new one; then the same for the next batch
    assert [(seq, envelope.read_header(data).key_id) for seq, data in writes] == [
        *((seq, old) for seq in first),
        *((seq, new) for seq in first),
        *((seq, old) for seq in second),
        *((seq, new) for seq in second),
    ]
    signed = {seq: envelope.read_header(data).header for seq, data in writes[:4] + writes[8:10]}
    assert {stored.seq: stored.header for stored in signing_portal.records} == signed
    assert [upload.status for upload in signing_portal.uploads] == [403, 201, 403, 201]


# --- the agents running -----------------------------------------------------------------------


@pytest.mark.process
def test_the_ros1_node_signs_what_the_simulated_robot_publishes(
    ros_master, tmp_path, pairing_key, signing_portal
):
    config = agent_yaml(
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
    assert_batch_signed(signing_portal, pairing_key, at_least=10)
    assert {stored.header["topic"] for stored in signing_portal.records} == {
        sim.ODOM_TOPIC,
        sim.IMAGE_TOPIC,
    }


@pytest.mark.process
def test_the_ros2_agent_signs_what_the_simulated_ros2_robot_publishes(
    ros2_env, tmp_path, pairing_key, signing_portal
):
    _, env = ros2_env
    config = agent_yaml(
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
    assert_batch_signed(signing_portal, pairing_key, at_least=10)
