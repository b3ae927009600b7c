"""Every record counted (provenance v2, ros_agent.batches): a paired robot's topic_seq, per
signer and topic, is never skipped and never reused, across a crash between the re-seal and
the upload, a crash in the middle of the re-seal's writes, an outage, a lost confirmation, a
restart, a refusal and a new pairing key; what was signed once leaves as those very bytes.

The agent is built as every agent is (ros_agent.pipeline, from its agent.yaml), on a real
spool on disk, against the in-test records endpoint that requires the paired robot's
signature. A crash is the objects dropped at that point (every write the agent made is on
disk already: each is synced before the next step), and the agent built again from the same
folder.
"""

import errno
import json
import logging
from pathlib import Path

import pytest
from std_msgs.msg import String

from ros_agent import LOGGER_NAME
from ros_agent.batches import TOPIC_SEQ_FILE, BatchSigner
from ros_agent.config import load_config
from ros_agent.counters import AgentCounters
from ros_agent.pipeline import Pipeline, pipeline_build
from ros_agent.sealing import RobotSigningKey, robot_signing_key
from ros_agent.spool import SpoolError
from ros_agent.uploader import Outcome
from ros_agent.wrapping import Recorder
from smcrypto import envelope, provenance
from tests.ros_agent.conftest import (
    OWNER,
    agent_yaml,
    assert_batch_signed,
    write_paired_robot_files,
)
from tests.support.records_server import RecordsServer

pytestmark = pytest.mark.timeout(120)

CHATTER, STATUS = "/chatter", "/status"
TOPICS = [(CHATTER, "std_msgs/String"), (STATUS, "std_msgs/String")]


class Crash(BaseException):
    """The agent's process dying at this point (nothing of the agent catches it)."""


def _agent(folder: Path, portal: RecordsServer, *, batch_size: int = 10) -> Pipeline:
    """The paired robot's agent in `folder` (its files as pairing left them), built anew."""
    config = agent_yaml(folder, portal, TOPICS, paired=True, batch_size=batch_size)
    return pipeline_build(load_config(config), backoff_max=0.05)


def _publish(pipeline: Pipeline, *topics: str) -> list[int]:
    return [
        pipeline.recorder.record(
            String(data=f"on {topic}"), topic=topic, ros_type="std_msgs/String"
        )
        for topic in topics
    ]


def _queued(folder: Path) -> dict[int, bytes]:
    """The envelopes in the spool's queue on disk, by seq."""
    return {
        int(path.stem): path.read_bytes() for path in (folder / "spool" / "queue").glob("*.env")
    }


def _counters_file(folder: Path) -> dict:
    path = folder / "spool" / TOPIC_SEQ_FILE
    return json.loads(path.read_text()) if path.exists() else {}


def _stored(portal: RecordsServer) -> dict[int, bytes]:
    return {record.seq: record.envelope for record in portal.records}


def _sent(portal: RecordsServer) -> list[list[int]]:
    return [upload.seqs for upload in portal.uploads if upload.status == 201]


def _signer(key: RobotSigningKey) -> str:
    return provenance.key_hash(key.public_key)


def test_each_batch_is_signed_once_and_each_topic_counted_from_zero(
    tmp_path, pairing_key, signing_portal
):
    agent = _agent(tmp_path, signing_portal, batch_size=10)
    try:
        _publish(agent, *[CHATTER, CHATTER, STATUS] * 8)  # 24 records, 16 and 8
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    streams = assert_batch_signed(signing_portal, pairing_key, at_least=24)
    assert streams == {CHATTER: list(range(16)), STATUS: list(range(8))}
    assert [len(seqs) for seqs in _sent(signing_portal)] == [10, 10, 4]
    headers = [record.header for record in signing_portal.records]
    assert len({header["sig"] for header in headers}) == 3  # one signature per batch
    assert [(h["sig_index"], h["sig_size"]) for h in headers] == [
        *((index, 10) for index in range(10)),
        *((index, 10) for index in range(10)),
        *((index, 4) for index in range(4)),
    ]
    assert _counters_file(tmp_path) == {_signer(pairing_key): {CHATTER: 16, STATUS: 8}}


def test_a_crash_between_the_reseal_and_the_upload_sends_the_same_bytes_then_numbers_on(
    tmp_path, pairing_key, signing_portal
):
    agent = _agent(tmp_path, signing_portal)
    _publish(agent, CHATTER, STATUS, CHATTER, CHATTER, STATUS)
    config = load_config(tmp_path / "agent.yaml")
    # what the uploader does first with the head batch, then the crash: nothing uploaded
    signer = BatchSigner(
        spool=agent.spool, keyring=config.keyring, signing_key=robot_signing_key(config)
    )
    signed = signer.ready(agent.spool.peek(10))
    agent.spool.close()
    del agent, signer
    on_disk = _queued(tmp_path)
    assert on_disk == {item.seq: item.envelope for item in signed}
    assert {envelope.read_header(data).provenance for data in on_disk.values()} == {"v2"}
    assert signing_portal.uploads == []

    agent = _agent(tmp_path, signing_portal)
    try:
        later = _publish(agent, STATUS, CHATTER, CHATTER)
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    assert _sent(signing_portal) == [sorted(on_disk), later]
    stored = _stored(signing_portal)
    assert {seq: stored[seq] for seq in on_disk} == on_disk  # the very bytes signed before
    streams = assert_batch_signed(signing_portal, pairing_key, at_least=8)
    assert streams == {CHATTER: [0, 1, 2, 3, 4], STATUS: [0, 1, 2]}


def test_a_crash_in_the_middle_of_the_reseal_writes_loses_no_number_and_reuses_none(
    tmp_path, pairing_key, signing_portal
):
    """Two of five envelopes of a batch written back signed, then the crash, before the
    counters file is: after the restart those two leave as they are (each verifies alone with
    its batch's signature and path), and the three others are signed as a batch of their own,
    numbered on from the written ones (the counters file alone is behind them)."""
    agent = _agent(tmp_path, signing_portal)
    _publish(agent, CHATTER, STATUS, CHATTER)
    assert agent.uploader.drain() is Outcome.EMPTY  # counted up to chatter 2, status 1
    recorded = _counters_file(tmp_path)
    _publish(agent, CHATTER, STATUS, CHATTER, STATUS, CHATTER)
    replace, written = agent.spool.replace, []

    def replace_then_crash(seq: int, data: bytes) -> None:
        if len(written) == 2:
            raise Crash
        replace(seq, data)
        written.append(seq)

    agent.spool.replace = replace_then_crash
    with pytest.raises(Crash):
        agent.uploader.deliver_next()
    agent.spool.close()
    del agent
    assert _counters_file(tmp_path) == recorded  # not yet written when it crashed
    on_disk = _queued(tmp_path)
    kinds = [envelope.read_header(on_disk[seq]).provenance for seq in sorted(on_disk)]
    assert kinds == ["v2", "v2", "unsigned", "unsigned", "unsigned"]

    agent = _agent(tmp_path, signing_portal)
    try:
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    first, rest = sorted(on_disk)[:2], sorted(on_disk)[2:]
    assert _sent(signing_portal)[1:] == [first, rest]
    stored = _stored(signing_portal)
    assert [stored[seq] for seq in first] == [on_disk[seq] for seq in first]
    assert [envelope.read_header(stored[seq]).header["sig_size"] for seq in first] == [5, 5]
    assert [envelope.read_header(stored[seq]).header["sig_size"] for seq in rest] == [3, 3, 3]
    streams = assert_batch_signed(signing_portal, pairing_key, at_least=8)
    assert streams == {CHATTER: [0, 1, 2, 3, 4], STATUS: [0, 1, 2]}
    assert _counters_file(tmp_path) == {_signer(pairing_key): {CHATTER: 5, STATUS: 3}}


def test_a_write_failing_in_the_middle_of_the_reseal_is_retried_without_a_reuse(
    tmp_path, pairing_key, signing_portal, caplog
):
    """A full disk while the batch is written back: nothing leaves; the envelopes written
    signed leave first as they are, the others are signed after them, numbered on."""
    agent = _agent(tmp_path, signing_portal)
    seqs = _publish(agent, CHATTER, CHATTER, STATUS, CHATTER)
    replace, calls = agent.spool.replace, []

    def replace_failing_once(seq: int, data: bytes) -> None:
        calls.append(seq)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        replace(seq, data)

    agent.spool.replace = replace_failing_once
    try:
        with caplog.at_level(logging.ERROR, logger=LOGGER_NAME):
            assert agent.uploader.deliver_next() is Outcome.RETRY
        assert signing_portal.uploads == []
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    assert "cannot write the signed batch" in caplog.text
    assert _sent(signing_portal) == [seqs[:2], seqs[2:]]
    streams = assert_batch_signed(signing_portal, pairing_key, at_least=4)
    assert streams == {CHATTER: [0, 1, 2], STATUS: [0]}


def test_an_outage_and_a_lost_confirmation_resend_the_same_signed_bytes(
    tmp_path, pairing_key, signing_portal, caplog
):
    agent = _agent(tmp_path, signing_portal, batch_size=4)
    try:
        seqs = _publish(agent, *[CHATTER, STATUS, CHATTER] * 2)
        signing_portal.stop()  # the portal is down: retried, never signed again
        assert agent.uploader.drain() is Outcome.RETRY
        signed_first = _queued(tmp_path)
        for _ in range(3):
            assert agent.uploader.drain() is Outcome.RETRY
        assert _queued(tmp_path) == signed_first
        signing_portal.start()
        signing_portal.fail_next(503, times=2)  # answered, but not stored
        assert agent.uploader.drain() is Outcome.RETRY
        assert agent.uploader.drain() is Outcome.RETRY
        signing_portal.lose_next()  # stored, and its 201 lost: sent again, the same bytes
        assert agent.uploader.drain() is Outcome.RETRY
        with caplog.at_level(logging.WARNING, logger=LOGGER_NAME):
            assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    assert "already has seq" in caplog.text
    assert agent.counters.failed == 0
    assert sorted(_stored(signing_portal)) == seqs  # each once
    first_batch = seqs[:4]
    assert {seq: _stored(signing_portal)[seq] for seq in first_batch} == {
        seq: signed_first[seq] for seq in first_batch
    }
    streams = assert_batch_signed(signing_portal, pairing_key, at_least=6)
    assert streams == {CHATTER: [0, 1, 2, 3], STATUS: [0, 1]}
    assert len({record.header["sig"] for record in signing_portal.records}) == 2


def test_a_restart_numbers_on_from_the_counters_file(tmp_path, pairing_key, signing_portal):
    for _ in range(3):  # each time the queue is empty when the agent stops
        agent = _agent(tmp_path, signing_portal)
        try:
            _publish(agent, CHATTER, STATUS, CHATTER)
            assert agent.uploader.drain() is Outcome.EMPTY
        finally:
            agent.spool.close()
        assert _queued(tmp_path) == {}

    streams = assert_batch_signed(signing_portal, pairing_key, at_least=9)
    assert streams == {CHATTER: list(range(6)), STATUS: [0, 1, 2]}
    assert len({record.header["sig"] for record in signing_portal.records}) == 3


def test_a_record_refused_for_good_keeps_its_number_and_its_batch_splits_without_resigning(
    tmp_path, owner_key, pairing_key, signing_portal, caplog
):
    """The portal refuses the batch (one record names another robot): sent again one by one,
    each record with its batch's signature and path, and it verifies alone; the refused one's
    number is a gap the portal will show as missing, and the log says so."""
    agent = _agent(tmp_path, signing_portal)
    config = load_config(tmp_path / "agent.yaml")
    stranger = Recorder(
        spool=agent.spool,
        keyring=config.keyring,
        owner=OWNER,
        robot="0b5d1c9e-0000-4000-8000-000000000001",
        counters=AgentCounters(),
    )
    try:
        _publish(agent, CHATTER, CHATTER)
        refused = stranger.record(String(data="x"), topic=CHATTER, ros_type="std_msgs/String")
        _publish(agent, CHATTER, STATUS)
        with caplog.at_level(logging.ERROR, logger=LOGGER_NAME):
            assert agent.uploader.drain() is Outcome.EMPTY
        _publish(agent, CHATTER)
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    assert agent.counters.failed == 1
    assert (tmp_path / "spool" / "rejected" / f"{refused:020d}.env").exists()
    assert "topic_seq 2 of /chatter" in caplog.text
    assert "missing" in caplog.text
    assert [upload.status for upload in signing_portal.uploads] == [
        403,
        201,
        201,
        403,
        201,
        201,
        201,
    ]
    batch = [record.header for record in signing_portal.records[:4]]
    assert len({header["sig"] for header in batch}) == 1
    assert [(header["sig_index"], header["sig_size"]) for header in batch] == [
        (0, 5),
        (1, 5),
        (3, 5),
        (4, 5),
    ]
    for record in signing_portal.records:  # each checked on its own
        header, plaintext = envelope.open(owner_key, record.envelope)
        provenance.signature_check(pairing_key.public_key, header, plaintext)
    numbers = [(r.header["topic"], r.header["topic_seq"]) for r in signing_portal.records]
    assert numbers == [(CHATTER, 0), (CHATTER, 1), (CHATTER, 3), (STATUS, 0), (CHATTER, 4)]


def test_a_new_pairing_key_counts_from_zero_and_signs_what_is_still_spooled(
    tmp_path, owner_key, pairing_key, signing_portal
):
    """Envelopes signed by the old key and never delivered are signed again by the key the
    robot has when they leave, counted from 0 under its own signer; the old key's counters
    stay in the file."""
    agent = _agent(tmp_path, signing_portal)
    _publish(agent, CHATTER, STATUS)
    config = load_config(tmp_path / "agent.yaml")
    BatchSigner(
        spool=agent.spool, keyring=config.keyring, signing_key=robot_signing_key(config)
    ).ready(agent.spool.peek(10))
    agent.spool.close()
    new_key = RobotSigningKey.of(write_paired_robot_files(tmp_path, owner_key))
    signing_portal.robot_public_key = new_key.public_key  # the robot paired again

    agent = _agent(tmp_path, signing_portal)
    try:
        _publish(agent, CHATTER)
        assert agent.uploader.drain() is Outcome.EMPTY
    finally:
        agent.spool.close()

    streams = assert_batch_signed(signing_portal, new_key, at_least=3)
    assert streams == {CHATTER: [0, 1], STATUS: [0]}
    assert _counters_file(tmp_path) == {
        _signer(pairing_key): {CHATTER: 1, STATUS: 1},
        _signer(new_key): {CHATTER: 2, STATUS: 1},
    }


def test_an_unreadable_counters_file_stops_the_agent_with_the_reason(
    tmp_path, pairing_key, signing_portal
):
    (tmp_path / "spool").mkdir()
    (tmp_path / "spool" / TOPIC_SEQ_FILE).write_text('{"abc": {"/chatter": -1}}')
    with pytest.raises(SpoolError, match="does not hold record counters"):
        _agent(tmp_path, signing_portal)
    (tmp_path / "spool" / TOPIC_SEQ_FILE).write_text("{}")
    _agent(tmp_path, signing_portal).spool.close()  # the spool was let go
