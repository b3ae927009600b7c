"""A paired robot's v2 batches against the real portal (live server, the session's anvil): the
agent as every agent is built (ros_agent.pipeline, a paired robot's agent.yaml), its robot
paired as the agent pairs (its key registered on chain). Every record is accepted, anchored,
and opened by its owner through the worker's check (chain, then the batch signature), each
batch under one signature, each topic counted from 0 without a gap, across an owner key
rotation (refused under the old key, re-sealed under the one the agent fetches, header kept)
and a restart of the agent.
"""

import logging
import uuid
from pathlib import Path

import pytest
import yaml
from std_msgs.msg import String

from accounts.services.keys import key_rotate, sm4_key_generate
from ros_agent import LOGGER_NAME
from ros_agent.config import load_config
from ros_agent.keyring import key_id_hex, write_keys_file
from ros_agent.pipeline import Pipeline, pipeline_build
from ros_agent.uploader import Outcome
from sharing.models import Access, Record
from sharing.verification.opening import records_open
from smcrypto import envelope, provenance
from tests.support.harness import wait_for
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(300)]

CHATTER, STATUS = "/chatter", "/status"


def _paired_robot_config(folder: Path, url: str, setup: RobotSetup) -> Path:
    """What pairing leaves on the robot of `setup`: its SM2 key, the owner's keys, its token,
    and agent.yaml naming them."""
    folder.mkdir(parents=True, exist_ok=True)
    private_key, _public_key = setup.signing_key
    (folder / "robot.sm2").write_text(private_key + "\n")
    (folder / "robot.sm2").chmod(0o600)
    write_keys_file(
        folder / "owner-keys.json", {key_id_hex(setup.key): setup.key}, key_id_hex(setup.key)
    )
    (folder / "robot.token").write_text(setup.token)
    (folder / "robot.token").chmod(0o600)
    settings = {
        "portal_url": url,
        "token_file": "robot.token",
        "robot": str(setup.robot.id),
        "owner": setup.owner.user.username,
        "sm2_key_file": "robot.sm2",
        "keys_file": "owner-keys.json",
        "topics": [{"name": CHATTER, "type": "std_msgs/String"}],
        "spool_dir": "spool",
        "batch_size": 10,
    }
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


def _publish(pipeline: Pipeline, *topics: str) -> None:
    for topic in topics:
        text = f"{topic} {uuid.uuid4().hex[:6]}"
        assert pipeline.recorder.record(String(data=text), topic=topic, ros_type="std_msgs/String")


def _deliver(config: Path, *topics: str) -> None:
    """The agent started, `topics` recorded and all of it delivered, the agent stopped."""
    pipeline = pipeline_build(load_config(config), backoff_max=0.5)
    try:
        _publish(pipeline, *topics)
        assert pipeline.uploader.drain() is Outcome.EMPTY
        assert pipeline.counters.failed == 0
    finally:
        pipeline.spool.close()


def test_a_paired_agents_batches_are_accepted_verified_and_counted_across_a_rotation(
    live_server, make_paired_robot, tmp_path, settings, caplog
):
    # an envelope captured after the rotation under the old key is refused: re-sealed
    settings.KEY_ROTATION_CLOCK_SKEW = 0
    setup = make_paired_robot()
    config = _paired_robot_config(tmp_path / "robot", live_server.url, setup)
    _deliver(config, *[CHATTER, CHATTER, STATUS] * 4)  # 12: batches of 10 and 2

    new_key = sm4_key_generate()
    key_rotate(owner=setup.owner, sm4_key=new_key)
    # the agent's log, read on its own logger: the portal's code in this process may set up
    # the root logger's handlers again
    agent_logger = logging.getLogger(LOGGER_NAME)
    agent_logger.addHandler(caplog.handler)
    try:
        _deliver(config, CHATTER, STATUS, CHATTER)  # the agent restarted, and the key rotated
    finally:
        agent_logger.removeHandler(caplog.handler)
    assert "re-sealed 3 envelope(s)" in caplog.text

    records = list(Record.objects.filter(robot=setup.robot).order_by("seq"))
    assert len(records) == 15
    wait_for(
        lambda: (
            Record.objects.filter(robot=setup.robot, status=Record.Status.ANCHORED).count() == 15
        ),
        timeout=60,
        what="the records anchored",
    )
    opened = records_open(
        records=records, viewer=setup.owner, kind=Access.Kind.PAGE, credential="session"
    )
    signer = provenance.key_hash(setup.signing_key[1])
    headers = []
    for record, item in zip(records, opened, strict=True):
        assert not isinstance(item, Exception), f"{record}: {item!r}"  # chain and signature hold
        assert record.signer == signer
        info = envelope.read_header(item.envelope)
        assert info.provenance == "v2"
        headers.append(info.header)
        provenance.signature_check(setup.signing_key[1], item.header, item.plaintext)

    batches = [headers[:10], headers[10:12], headers[12:]]
    assert [len({header["sig"] for header in batch}) for batch in batches] == [1, 1, 1]
    assert len({header["sig"] for header in headers}) == 3
    assert [[header["sig_size"] for header in batch] for batch in batches] == [
        [10] * 10,
        [2] * 2,
        [3] * 3,
    ]
    streams: dict[str, list[int]] = {}
    for header in headers:
        streams.setdefault(header["topic"], []).append(header["topic_seq"])
    assert streams == {CHATTER: list(range(10)), STATUS: list(range(5))}
    # the last batch, sealed under the old key after the rotation, reached the portal re-sealed
    assert {envelope.read_header(item.envelope).key_id for item in opened[12:]} == {
        envelope.key_id(new_key)
    }
    assert {envelope.read_header(item.envelope).key_id for item in opened[:12]} == {
        envelope.key_id(setup.key)
    }


def test_a_robot_that_lost_its_spool_is_refused_and_told_to_pair_again(
    live_server, make_paired_robot, tmp_path, caplog
):
    """The counters live with the spool: a robot whose spool was wiped counts from 0 again
    under the same key, which the portal refuses (409 topic_seq_reused, nothing stored), and
    the agent says what to do rather than leaving the owner to guess."""
    setup = make_paired_robot()
    config = _paired_robot_config(tmp_path / "robot", live_server.url, setup)
    _deliver(config, CHATTER, CHATTER)
    assert Record.objects.filter(robot=setup.robot).count() == 2

    # the spool wiped: a new spool directory, the same key and token
    settings = yaml.safe_load(config.read_text())
    settings["spool_dir"] = "spool-after-loss"
    config.write_text(yaml.safe_dump(settings))
    agent_logger = logging.getLogger(LOGGER_NAME)
    agent_logger.addHandler(caplog.handler)
    try:
        pipeline = pipeline_build(load_config(config), backoff_max=0.5)
        try:
            _publish(pipeline, CHATTER)
            assert pipeline.uploader.drain() is Outcome.EMPTY
            assert pipeline.counters.failed == 1
        finally:
            pipeline.spool.close()
    finally:
        agent_logger.removeHandler(caplog.handler)

    assert "topic_seq_reused" in caplog.text
    assert "Pair the robot again" in caplog.text
    assert Record.objects.filter(robot=setup.robot).count() == 2
    assert list(
        Record.objects.filter(robot=setup.robot)
        .order_by("topic_seq")
        .values_list("topic_seq", flat=True)
    ) == [0, 1]
