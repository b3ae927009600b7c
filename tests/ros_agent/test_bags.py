"""`python -m ros_agent import`: recordings written here with rosbags' writers (ROS 1 .bag,
ROS 2 .db3 and .mcap) go through the real import, the real spool and uploader, to the real
portal (live server, the session's anvil); every message is then opened in the portal as its
owner (integrity check, decryption) and compared with what was recorded, capture time
included. Imported again, nothing is uploaded twice. Damaged files, unknown types and topics
the config does not name are reported, the rest imported, and no traceback reaches the user.
"""

import base64
import re
import shutil
import sqlite3
import subprocess
import sys
from pathlib import Path
from random import Random

import pytest
import yaml
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import get_types_from_msg

from accounts.models import Robot
from ros_agent import bags, ros2msg
from ros_agent.spool import Spool
from sharing.models import Record
from stack.anvil import free_port
from tests.ros_agent.conftest import REPO_ROOT, write_key_file
from tests.support.custom_msgs import (
    INSPECTION,
    INSPECTION_TOPIC,
    MSG_DIR,
    inspection,
    inspection_record,
)
from tests.support.portal_checks import opened_records, robot_config, stamp_time
from tests.support.recordings import (
    ODOM,
    TOPICS,
    Sample,
    comparable,
    expected_data,
    make_samples,
    ros1_store,
    ros2_store,
    write_ros1_bag,
    write_ros2_bag,
)

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(300)]

PER_TOPIC = 3
SECOND = 10**9


def _import(config: Path, *files: Path, capsys) -> tuple[int, str]:
    code = bags.main(
        ["--config", str(config), "--no-progress", "--upload-timeout", "60", *map(str, files)]
    )
    out, err = capsys.readouterr()
    assert not _our_tracebacks(out + err)
    return code, out + err


def _our_tracebacks(text: str) -> list[str]:
    """Traceback frames in the agent's code. (Not the whole stderr: Celery, running eagerly in
    the live server's thread, may leave a log handler on a stream pytest closed, whose
    '--- Logging error ---' reports carry a traceback of their own.)"""
    return re.findall(r'File "[^"]*/ros_agent/[^"]*"', text)


def _check_stored(robot, expected: list[tuple[Sample, bool]]) -> None:
    """Every expected sample is stored once, at its capture time, with its recorded values."""
    by_key = {
        (sample.topic, stamp_time(sample.stamp_ns)): (sample, ros1) for sample, ros1 in expected
    }
    stored = opened_records(robot, expected=len(expected))
    seen = set()
    for record, document in stored:
        key = (record.topic, record.captured_at)
        assert key in by_key, f"unexpected record {key}"
        assert key not in seen, f"stored twice: {key}"
        seen.add(key)
        sample, ros1 = by_key[key]
        assert document["Topic"] == sample.topic
        assert document["Type"] == record.data_type == sample.ros_type
        assert document["Time"] == record.captured_at.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        assert comparable(document["K"]) == expected_data(sample, ros1=ros1), key
        if sample.has_header:
            assert document["K"]["header"]["stamp"]["iso"] == document["Time"]


def _check_against_an_independent_mcap_decoder(path: Path, robot) -> None:
    """The portal's records of an .mcap file hold what the `mcap-ros2-support` decoder (not
    rosbags) reads from it: stamps, poses, pixels' bytes, strings."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    stored = {
        (record.topic, record.captured_at): document["K"]
        for record, document in opened_records(robot, expected=robot.records.count())
    }
    with path.open("rb") as stream:
        decoded = list(
            make_reader(stream, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        )
    assert len(decoded) == len(TOPICS) * PER_TOPIC
    for _, channel, message, msg in decoded:
        topic = channel.topic
        data = stored[(topic, stamp_time(message.log_time))]
        if hasattr(msg, "header"):
            stamp = data["header"]["stamp"]
            assert (stamp["secs"], stamp["nsecs"]) == (
                msg.header.stamp.sec,
                msg.header.stamp.nanosec,
            )
            assert data["header"]["frame_id"] == msg.header.frame_id
        if topic == ODOM[0]:
            position = msg.pose.pose.position
            assert data["position"] == {"x": position.x, "y": position.y, "z": position.z}
            assert data["pose_covariance"] == list(msg.pose.covariance)
        elif topic == "/camera/compressed":
            assert base64.b64decode(data["data"]) == bytes(msg.data)
        elif topic == "/points":
            assert base64.b64decode(data["data"]) == bytes(msg.data)
            assert [f["name"] for f in data["fields"]] == [f.name for f in msg.fields]
        elif topic == "/chatter":
            assert data == {"data": msg.data}


@pytest.fixture
def robot_setup(live_server, make_robot, tmp_path):
    setup = make_robot()
    # /secret is named, but no recording defines its type: the unknown-type case.
    topics = (*TOPICS, ("/secret", "my_pkg/Secret"))
    config = robot_config(tmp_path / "robot", url=live_server.url, setup=setup, topics=topics)
    return setup, config


def test_ros1_and_ros2_recordings_are_imported_once_and_open_to_what_was_recorded(
    robot_setup, tmp_path, capsys
):
    setup, config = robot_setup
    ts1, ts2 = ros1_store(), ros2_store()
    ros1 = make_samples(ts1, PER_TOPIC, base_ns=1_700_000_000 * SECOND + 123_456_789)
    sqlite = make_samples(ts2, PER_TOPIC, base_ns=1_700_000_100 * SECOND + 5_000)
    mcap = make_samples(ts2, PER_TOPIC, base_ns=1_700_000_200 * SECOND + 999_999_999)
    files = [
        write_ros1_bag(tmp_path / "drive.bag", ros1, ts1),
        write_ros2_bag(tmp_path / "drive_db3", sqlite, ts2, mcap=False),
        write_ros2_bag(tmp_path / "drive_mcap", mcap, ts2, mcap=True),
    ]
    assert [f.suffix for f in files] == [".bag", ".db3", ".mcap"]

    code, output = _import(config, *files, capsys=capsys)
    assert code == 0, output
    total = 3 * len(TOPICS) * PER_TOPIC
    assert f"total: {total} message(s) sealed" in output
    assert f"uploaded {total}, refused by the portal 0, waiting in the spool 0" in output
    for topic, _ in TOPICS:
        assert f"  {topic}: {PER_TOPIC}" in output
    expected = [(s, True) for s in ros1] + [(s, False) for s in sqlite + mcap]
    _check_stored(setup.robot, expected)
    _check_against_an_independent_mcap_decoder(files[2], setup.robot)
    last_seq = Robot.objects.get(pk=setup.robot.pk).last_seq

    # Imported again, also under another name and as rosbag2 folders: recognised by content,
    # nothing sent.
    copy = tmp_path / "copy-of-drive.bag"
    shutil.copy(files[0], copy)
    folders = [files[1].parent, files[2].parent]
    code, output = _import(config, *files, copy, *folders, capsys=capsys)
    assert code == 0, output
    assert "total: 0 message(s) sealed" in output
    assert output.count("was imported before (same file content)") == 6 * len(TOPICS)
    assert Record.objects.filter(robot=setup.robot).count() == total
    assert Robot.objects.get(pk=setup.robot.pk).last_seq == last_seq


def _importer_stopping_after(config: Path, count: int, stop) -> bags.BagImporter:
    """An importer whose `stop()` is called once it has sealed `count` messages."""
    importer = bags.BagImporter(bags.load_config(config), progress=False)
    original_seal = importer._seal

    def seal_then_stop(*args, **kwargs):
        original_seal(*args, **kwargs)
        if importer.counters.spooled >= count:
            stop(importer)

    importer._seal = seal_then_stop
    return importer


def test_an_interrupted_import_continues_where_it_stopped(robot_setup, tmp_path, capsys):
    setup, config = robot_setup
    ts2 = ros2_store()
    samples = make_samples(ts2, 4)
    recording = write_ros2_bag(tmp_path / "long", samples, ts2, mcap=True)
    stop_after = 10
    importer = _importer_stopping_after(config, stop_after, lambda i: i.stopping.set())  # Ctrl-C
    (report,) = importer.run([recording], upload_timeout=0)
    assert report.imported == stop_after
    assert "interrupted" in report.stopped
    # The rest, and only the rest, on the next run; then nothing.
    code, output = _import(config, recording, capsys=capsys)
    assert code == 0, output
    assert f"total: {len(samples) - stop_after} message(s) sealed" in output
    assert "cut off" not in output  # a clean stop: nothing to check
    _check_stored(setup.robot, [(s, False) for s in samples])
    code, output = _import(config, recording, capsys=capsys)
    assert "total: 0 message(s) sealed" in output
    assert Record.objects.filter(robot=setup.robot).count() == len(samples)


class _PowerCut(BaseException):
    """The process ends here: nothing after it runs (no ledger written)."""


def test_after_a_hard_kill_the_next_import_sends_nothing_twice(
    robot_setup, tmp_path, capsys, monkeypatch
):
    setup, config = robot_setup
    monkeypatch.setattr(bags, "LEDGER_EVERY", 4)
    ts2 = ros2_store()
    samples = make_samples(ts2, 3)
    recording = write_ros2_bag(tmp_path / "long", samples, ts2, mcap=False)

    def power_cut(_importer):
        raise _PowerCut

    importer = _importer_stopping_after(config, 10, power_cut)
    with pytest.raises(_PowerCut):
        importer.run([recording], upload_timeout=30)
    # Ten sealed and sent, the ledger last written after eight.
    assert Record.objects.filter(robot=setup.robot).count() == 10
    code, output = _import(config, recording, capsys=capsys)
    assert code == 0, output
    assert "skipped 2: sent by an earlier import that was cut off" in output
    assert f"total: {len(samples) - 10} message(s) sealed" in output
    _check_stored(setup.robot, [(s, False) for s in samples])


def _recording_with_trouble(folder: Path, ts, samples: list[Sample]) -> Path:
    """A .db3 with the samples, one of them damaged, a topic the config does not name and a
    type the file has no definition of."""
    ts.register(get_types_from_msg("string secret\nint32 level\n", "my_pkg/msg/Secret"))
    with Ros2Writer(folder, version=9) as writer:
        connections = {}
        for sample in samples:
            ros2_type = sample.msg.__msgtype__
            if sample.topic not in connections:
                connections[sample.topic] = writer.add_connection(
                    sample.topic, ros2_type, typestore=ts
                )
            writer.write(
                connections[sample.topic], sample.stamp_ns, ts.serialize_cdr(sample.msg, ros2_type)
            )
        other = writer.add_connection("/not_configured", "std_msgs/msg/String", typestore=ts)
        secret = writer.add_connection("/secret", "my_pkg/msg/Secret", typestore=ts)
        for i in range(2):
            writer.write(
                other,
                5 + i,
                ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"),
            )
            msg = ts.types["my_pkg/msg/Secret"](secret="s", level=i)
            writer.write(secret, 7 + i, ts.serialize_cdr(msg, "my_pkg/msg/Secret"))
    (db3,) = folder.glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("DELETE FROM message_definitions WHERE topic_type = 'my_pkg/msg/Secret'")
        topic_id = db.execute("SELECT id FROM topics WHERE name = ?", (ODOM[0],)).fetchone()[0]
        first = db.execute(
            "SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp LIMIT 1", (topic_id,)
        ).fetchone()[0]
        db.execute("UPDATE messages SET data = x'00010000ffff' WHERE id = ?", (first,))
    return db3


def _sealed(output: str, path: Path) -> int:
    """How many messages the summary says were sealed from `path`."""
    line = next(line for line in output.splitlines() if line.startswith(f"{path}: "))
    return int(line.split(": ")[1].split(" ")[0])


def _stored_from(robot, samples: list[Sample]) -> list[Sample]:
    stored = {(r.topic, r.captured_at) for r in Record.objects.filter(robot=robot)}
    return [s for s in samples if (s.topic, stamp_time(s.stamp_ns)) in stored]


def test_bad_recordings_are_reported_and_the_rest_imported(robot_setup, tmp_path, capsys):
    setup, config = robot_setup
    ts1, ts2 = ros1_store(), ros2_store()
    good = make_samples(ts2, 2, base_ns=1_700_000_300 * SECOND)
    troubled = _recording_with_trouble(tmp_path / "troubled", ts2, good)
    # Cut off half way (a recorder that lost power): no index, no summary.
    cut_ros1 = make_samples(ts1, 10, base_ns=1_700_000_400 * SECOND)
    data = write_ros1_bag(tmp_path / "whole.bag", cut_ros1, ts1).read_bytes()
    truncated = tmp_path / "truncated.bag"
    truncated.write_bytes(data[: len(data) // 2])
    cut_mcap = make_samples(ts2, 10, base_ns=1_700_000_500 * SECOND)
    data = write_ros2_bag(tmp_path / "whole_mcap", cut_mcap, ts2, mcap=True).read_bytes()
    truncated_mcap = tmp_path / "truncated.mcap"
    truncated_mcap.write_bytes(data[: len(data) // 2])
    # What `rosbag record` leaves when it dies: the .bag.active it was writing.
    died = make_samples(ts1, 6, base_ns=1_700_000_700 * SECOND)
    data = write_ros1_bag(tmp_path / "whole3.bag", died, ts1).read_bytes()
    active = tmp_path / "2025-06-01-10-00-00.bag.active"
    active.write_bytes(data[: len(data) * 6 // 10])
    # The index intact, but the record header of the sixth odometry message overwritten.
    broken = make_samples(ts1, 10, base_ns=1_700_000_600 * SECOND)
    data = write_ros1_bag(tmp_path / "whole2.bag", broken, ts1).read_bytes()
    sixth = next(x for x in broken if (x.topic, x.ros_type) == ODOM and x.index == 5)
    at = data.index(ts1.serialize_ros1(sixth.msg, sixth.msg.__msgtype__))
    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(data[: at - 64] + b"\xff" * 64 + data[at:])
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)
    notes = tmp_path / "notes.txt"
    notes.write_text("not a recording")
    missing = tmp_path / "missing.db3"

    files = [troubled, truncated, truncated_mcap, active, damaged, garbage, notes, missing]
    code, output = _import(config, *files, capsys=capsys)
    assert code == 1, output
    assert f"{garbage}: refused: not a readable recording" in output
    assert f"{notes}: refused: .txt: not a recording" in output
    assert f"{missing}: refused: no such file or folder" in output
    assert "skipped 1: a nav_msgs/Odometry message on /robot/odom does not decode" in output
    assert "skipped 2: topic /not_configured is not in the config" in output
    assert "skipped 2: unknown message type my_pkg/msg/Secret on /secret" in output
    assert output.count("note: read without its index, which is damaged or missing") == 3
    assert output.count("the file is damaged or cut off after message") == 4

    # Stored: every good message of the troubled file (not the damaged one), and what the
    # cut-off and damaged files held before the break, each whole and as recorded.
    odom_first = min(s.stamp_ns for s in good if (s.topic, s.ros_type) == ODOM)
    expected = [
        (s, False) for s in good if not ((s.topic, s.ros_type) == ODOM and s.stamp_ns == odom_first)
    ]
    for path, samples, ros1 in (
        (truncated, cut_ros1, True),
        (truncated_mcap, cut_mcap, False),
        (active, died, True),
        (damaged, broken, True),
    ):
        sealed = _sealed(output, path)
        assert 0 < sealed < len(samples), (path, sealed)
        stored = _stored_from(setup.robot, samples)
        assert len(stored) == sealed, path
        expected += [(s, ros1) for s in stored]
    _check_stored(setup.robot, expected)
    assert not Record.objects.filter(robot=setup.robot, topic__in=["/secret", "/not_configured"])

    # What could be read of them is all there is: imported again, nothing is sent.
    code, output = _import(config, *files[:5], capsys=capsys)
    assert "total: 0 message(s) sealed" in output
    assert Record.objects.filter(robot=setup.robot).count() == len(expected)


@pytest.mark.process
def test_the_command_line_refuses_while_the_robots_agent_holds_the_spool(robot_setup, tmp_path):
    _, config = robot_setup
    ts2 = ros2_store()
    recording = write_ros2_bag(tmp_path / "r", make_samples(ts2, 1)[:1], ts2, mcap=True)
    held = Spool(tmp_path / "robot" / "spool", max_bytes=10**6)  # as a running agent does
    try:
        answer = subprocess.run(
            [sys.executable, "-m", "ros_agent", "import", "--config", str(config), str(recording)],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    finally:
        held.close()
    assert answer.returncode == 2, answer.stderr
    assert "is in use by another agent" in answer.stderr
    assert "stop the agent first" in answer.stderr
    assert "Traceback" not in answer.stderr + answer.stdout
    assert not Record.objects.exists()


def test_with_the_portal_away_the_import_keeps_the_envelopes_for_the_next_run(
    robot_setup, tmp_path, capsys
):
    setup, config = robot_setup
    settings = yaml.safe_load(config.read_text())
    offline = config.with_name("offline.yaml")
    offline.write_text(
        yaml.safe_dump({**settings, "portal_url": f"http://127.0.0.1:{free_port()}"})
    )
    ts2 = ros2_store()
    samples = make_samples(ts2, 1)
    recording = write_ros2_bag(tmp_path / "r", samples, ts2, mcap=True)
    code = bags.main(
        ["--config", str(offline), "--no-progress", "--upload-timeout", "1", str(recording)]
    )
    output = capsys.readouterr().out
    assert code == 3, output
    assert f"uploaded 0, refused by the portal 0, waiting in the spool {len(samples)}" in output
    assert not Record.objects.exists()
    # The portal back: the next import sends what waited, and nothing of the file again.
    code, output = _import(config, recording, capsys=capsys)
    assert code == 0, output
    assert "total: 0 message(s) sealed" in output
    assert f"uploaded {len(samples)}, refused by the portal 0, waiting in the spool 0" in output
    _check_stored(setup.robot, [(s, False) for s in samples])


@pytest.mark.process
def test_randomly_damaged_recordings_never_end_in_a_traceback(tmp_path):
    """Bytes flipped, cut or repeated anywhere in each kind of recording: every file is
    imported in part, refused, or imported whole, with a message; the command never fails."""
    ts1, ts2 = ros1_store(), ros2_store()
    originals = [
        write_ros1_bag(tmp_path / "o.bag", make_samples(ts1, 2), ts1).read_bytes(),
        write_ros2_bag(tmp_path / "o_db3", make_samples(ts2, 2), ts2, mcap=False).read_bytes(),
        write_ros2_bag(tmp_path / "o_mcap", make_samples(ts2, 2), ts2, mcap=True).read_bytes(),
    ]
    random = Random(17)
    files = []
    for number in range(45):
        suffix = (".bag", ".db3", ".mcap")[number % 3]
        data = bytearray(originals[number % 3])
        at = random.randrange(len(data))
        match number % 5:
            case 0:
                data = data[:at]
            case 1:
                data[at : at + 16] = bytes(random.randrange(256) for _ in range(16))
            case 2:
                data[at : at + 4] = b"\xff\xff\xff\x7f"
            case 3:
                data = data[:at] + data[at : at + 200] * 3 + data[at + 200 :]
            case 4:
                data[at] ^= 0x40
        path = tmp_path / f"damaged{number}{suffix}"
        path.write_bytes(bytes(data))
        files.append(path)
    (tmp_path / "robot").mkdir()
    key = write_key_file(tmp_path / "robot" / "k.sm4", bytes(16))
    config = tmp_path / "robot" / "agent.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "portal_url": f"http://127.0.0.1:{free_port()}",  # nobody: envelopes wait
                "token": "t",
                "robot": "r",
                "owner": "o",
                "key_file": str(key),
                "topics": [{"name": name, "type": ros_type} for name, ros_type in TOPICS],
                "spool_dir": "spool",
            }
        )
    )
    command = ["import", "--config", str(config), "--no-progress", "--upload-timeout", "0"]
    answer = subprocess.run(
        [sys.executable, "-m", "ros_agent", *command, *map(str, files)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert answer.returncode in (1, 3), answer.stdout + answer.stderr
    assert "Traceback" not in answer.stdout + answer.stderr
    for path in files:
        assert f"{path}: " in answer.stdout


def test_a_full_spool_with_the_portal_away_stops_the_import_until_the_next_run(
    robot_setup, tmp_path, capsys
):
    setup, config = robot_setup
    settings = yaml.safe_load(config.read_text())
    offline = config.with_name("offline.yaml")
    offline.write_text(
        yaml.safe_dump(
            {
                **settings,
                "portal_url": f"http://127.0.0.1:{free_port()}",
                "spool_max_bytes": 12_000,
            }
        )
    )
    ts2 = ros2_store()
    samples = make_samples(ts2, 3)
    recording = write_ros2_bag(tmp_path / "r", samples, ts2, mcap=True)
    importer = bags.BagImporter(bags.load_config(offline), progress=False, stall_timeout=0.5)
    (report,) = importer.run([recording], upload_timeout=0)
    assert "the spool is full" in report.stopped
    assert 0 < report.imported < len(samples)
    assert "the spool had no room" not in report.skipped  # it stopped instead of dropping
    # The portal reachable again: what waited goes first, then the rest of the file.
    code, output = _import(config, recording, capsys=capsys)
    assert code == 0, output
    assert f"total: {len(samples) - report.imported} message(s) sealed" in output
    _check_stored(setup.robot, [(s, False) for s in samples])


def test_a_custom_type_the_recording_does_not_define_is_learned_from_msg_files(
    live_server, make_robot, tmp_path, capsys
):
    """A .db3 of a robot's own nested type without its definitions (as Humble's recorder
    writes them): the import learns the type from the `.msg` folder agent.yaml names, and
    each record opens to every field."""
    setup = make_robot()
    config = robot_config(
        tmp_path / "robot",
        url=live_server.url,
        setup=setup,
        topics=[(INSPECTION_TOPIC, INSPECTION)],
        msg_dirs=[str(MSG_DIR)],
    )
    ts = ros2msg.default_typestore()
    inspection_type = ros2msg.ros2_name(INSPECTION)
    ros2msg.learn_message_types(ts, [inspection_type], [MSG_DIR])
    with Ros2Writer(tmp_path / "inspections", version=9) as writer:
        connection = writer.add_connection(INSPECTION_TOPIC, inspection_type, typestore=ts)
        for index in range(PER_TOPIC):
            data = ts.serialize_cdr(inspection(ts, index), inspection_type)
            writer.write(connection, (1_767_225_600 + index) * SECOND, data)
    (db3,) = (tmp_path / "inspections").glob("*.db3")
    with sqlite3.connect(db3) as db:
        db.execute("DELETE FROM message_definitions WHERE topic_type LIKE 'authros_test_msgs/%'")

    code, output = _import(config, db3, capsys=capsys)
    assert code == 0, output
    assert f"total: {PER_TOPIC} message(s) sealed" in output
    documents = [document for _, document in opened_records(setup.robot, expected=PER_TOPIC)]
    assert sorted((d["K"] for d in documents), key=lambda k: k["round"]) == [
        inspection_record(index) for index in range(PER_TOPIC)
    ]
