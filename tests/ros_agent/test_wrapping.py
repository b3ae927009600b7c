"""Recorder: message -> Fig. 4 JSON -> envelope v1 with the next seq -> spool."""

import json
import logging
from datetime import UTC, datetime

import genpy
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Image
from std_msgs.msg import String

from ros_agent.counters import AgentCounters, worth_logging
from ros_agent.spool import Spool
from ros_agent.wrapping import Recorder
from smcrypto import envelope
from tests.ros_agent.conftest import OWNER, ROBOT

RECEIVED = datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC)


def _recorder(tmp_path, key, **spool_options) -> tuple[Recorder, Spool, AgentCounters]:
    spool = Spool(tmp_path / "spool", max_bytes=spool_options.get("max_bytes", 10**6), seq_floor=0)
    counters = AgentCounters()
    recorder = Recorder(spool=spool, key=key, owner=OWNER, robot=ROBOT, counters=counters)
    return recorder, spool, counters


def test_a_message_is_sealed_as_the_fig4_record_with_the_next_seq(tmp_path, owner_key):
    recorder, spool, counters = _recorder(tmp_path, owner_key)

    seqs = [
        recorder.record(
            String(data=text), topic="/chatter", ros_type="std_msgs/String", received_at=RECEIVED
        )
        for text in ("hello", "wörld")
    ]

    assert seqs == [0, 1]
    items = spool.peek(10)
    header, plaintext = envelope.open(owner_key, items[1].envelope)
    assert header == {
        "owner": OWNER,
        "robot": ROBOT,
        "topic": "/chatter",
        "type": "std_msgs/String",
        "seq": 1,
        "time": "2026-11-21T14:00:00.123456Z",
    }
    assert (
        plaintext
        == (
            '{"K":{"data":"wörld"},"Owner":"alice","Time":"2026-11-21T14:00:00.123456Z",'
            '"Type":"std_msgs/String","Topic":"/chatter"}'
        ).encode()
    )
    assert counters.snapshot() == {"spooled": 2, "sent": 0, "failed": 0, "dropped": 0}


def test_capture_time_is_the_header_stamp_when_there_is_one(tmp_path, owner_key):
    recorder, spool, _ = _recorder(tmp_path, owner_key)
    msg = Odometry()
    msg.header.stamp = genpy.Time(1795272613, 728813999)

    recorder.record(msg, topic="/robot/odom", ros_type="nav_msgs/Odometry", received_at=RECEIVED)

    header, plaintext = envelope.open(owner_key, spool.peek(1)[0].envelope)
    record = json.loads(plaintext)
    assert header["time"] == record["Time"] == "2026-11-21T14:50:13.728813Z"
    assert record["K"]["header"]["stamp"]["iso"] == header["time"]


def test_a_message_that_cannot_be_converted_is_counted_and_logged(tmp_path, owner_key, caplog):
    recorder, spool, counters = _recorder(tmp_path, owner_key)
    msg = Image(height=1, width=1, encoding="yuv422", step=2, data=b"\0\0")

    with caplog.at_level(logging.ERROR):
        assert recorder.record(msg, topic="/cam", ros_type="sensor_msgs/Image") is None

    assert len(spool) == 0
    assert counters.failed == 1
    assert "cannot record a sensor_msgs/Image message from /cam" in caplog.text
    assert "'yuv422' is not supported" in caplog.text


def test_a_full_spool_drops_new_messages_says_so_and_keeps_the_old(tmp_path, owner_key, caplog):
    recorder, spool, counters = _recorder(tmp_path, owner_key, max_bytes=1000)
    with caplog.at_level(logging.WARNING):
        seqs = [
            recorder.record(String(data="x" * 100), topic="/c", ros_type="std_msgs/String")
            for _ in range(6)
        ]
    kept = [seq for seq in seqs if seq is not None]
    assert kept == list(range(len(kept)))
    assert 2 <= len(kept) < 6
    assert counters.dropped == 6 - len(kept)
    assert caplog.text.count("is full") == 1  # once, not per message
    assert "dropped 1 new message(s)" in caplog.text

    spool.ack(spool.peek(10))
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        recorder.record(String(data="x"), topic="/c", ros_type="std_msgs/String")
    assert "room again after dropping" in caplog.text
    assert len(spool) == 1


def test_a_closed_recorder_records_nothing(tmp_path, owner_key):
    recorder, spool, _ = _recorder(tmp_path, owner_key)
    recorder.close()
    assert recorder.record(String(data="late"), topic="/c", ros_type="std_msgs/String") is None
    assert len(spool) == 0


def test_repeated_trouble_is_logged_at_powers_of_ten():
    assert [n for n in range(1, 2001) if worth_logging(n)] == [1, 10, 100, 1000]
