"""What the suite's owner and robot fixtures (tests/conftest.py) hand a test: the password
every test owner has, a robot with its owner, key and token (RobotSetup, PairedRobot), and
envelopes sealed as the robot's agent would seal them (seal_for)."""

import json
from dataclasses import dataclass
from datetime import UTC, datetime

from accounts.models import Owner, Robot
from smcrypto import envelope, provenance

TEST_PASSWORD = "correct horse battery staple 42"


def seal_for(
    robot: Robot,
    key: bytes,
    *,
    seq: int,
    topic: str = "/robot/odom",
    data_type: str = "nav_msgs/Odometry",
    plaintext: bytes | None = None,
    owner: str | None = None,
    robot_id: str | None = None,
    time: str | None = None,
    signing_key: tuple[str, str] | None = None,
) -> bytes:
    """An envelope as the robot's agent would seal it, signed with `signing_key` (the robot's
    SM2 private and public key, hex) when given, as a paired robot signs."""
    header = {
        "owner": owner or robot.owner.username,
        "robot": robot_id or str(robot.id),
        "topic": topic,
        "type": data_type,
        "seq": seq,
        "time": time or datetime.now(tz=UTC).isoformat().replace("+00:00", "Z"),
    }
    body = plaintext if plaintext is not None else json.dumps({"K": {"seq": seq}}).encode()
    if signing_key is not None:
        header = provenance.sign_header(*signing_key, header, body)
    return envelope.seal(key, header, body)


@dataclass
class RobotSetup:
    owner: Owner
    key: bytes
    robot: Robot
    token: str
    # A paired robot's SM2 key pair (private, public hex): its envelopes are signed.
    signing_key: tuple[str, str] | None = None

    def seal(self, seq: int, **kwargs: object) -> bytes:
        kwargs.setdefault("signing_key", self.signing_key)
        return seal_for(self.robot, self.key, seq=seq, **kwargs)


@dataclass(frozen=True)
class PairedRobot:
    robot: Robot
    token: str
    signing_key: tuple[str, str]  # its SM2 key pair (private, public hex)
