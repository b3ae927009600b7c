"""A robot against the real portal (live server, the session's anvil): its config, and reading
back what it stored, integrity-checked and decrypted as its owner."""

import json
from datetime import UTC, datetime, timedelta
from pathlib import Path

import yaml

from sharing.models import Access, Record
from sharing.verification.opening import records_open
from tests.ros_agent.conftest import write_key_file
from tests.support.harness import wait_for
from tests.support.recordings import TOPICS

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def robot_config(folder: Path, *, url: str, setup, topics=TOPICS, **extra) -> Path:
    """agent.yaml for the robot of `setup` (tests.support.robot_setup.RobotSetup) sent to `url`."""
    folder.mkdir(parents=True, exist_ok=True)
    write_key_file(folder / "owner.sm4", setup.key)
    token_file = folder / "robot.token"
    token_file.write_text(setup.token)
    token_file.chmod(0o600)
    config = {
        "portal_url": url,
        "token_file": "robot.token",
        "robot": str(setup.robot.id),
        "owner": setup.owner.user.username,
        "key_file": "owner.sm4",
        "topics": [{"name": name, "type": ros_type} for name, ros_type in topics],
        "spool_dir": "spool",
        "batch_size": 20,
        "flush_interval": 0.2,
        "backoff_max": 1.0,
        "stats_interval": 1.0,
        "shutdown_flush": 10.0,
        **extra,
    }
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def stamp_time(ns: int) -> datetime:
    """A ROS stamp as the portal stores a capture time (microseconds)."""
    return _EPOCH + timedelta(microseconds=ns // 1000)


def opened_records(robot, *, expected: int, timeout: float = 60) -> list[tuple[Record, dict]]:
    """The robot's records once `expected` are stored and anchored, each opened by its owner
    (the integrity check against the chain, then decryption): (record, Fig. 4 document)."""
    wait_for(
        lambda: Record.objects.filter(robot=robot).count() >= expected,
        timeout=timeout,
        what=f"{expected} records of the robot",
    )
    records = list(Record.objects.filter(robot=robot).order_by("seq"))
    assert len(records) == expected, f"{len(records)} records, expected {expected}"
    wait_for(
        lambda: (
            Record.objects.filter(robot=robot, status=Record.Status.ANCHORED).count() == expected
        ),
        timeout=timeout,
        what="the records anchored",
    )
    opened = records_open(
        records=records, viewer=records[0].owner, kind=Access.Kind.PAGE, credential="session"
    )
    result = []
    for record, item in zip(records, opened, strict=True):
        assert not isinstance(item, Exception), f"{record}: {item!r}"
        result.append((record, json.loads(item.plaintext)))
    return result
