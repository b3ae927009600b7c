"""Sealing a record as this robot, and the robot's signing key.

The agent seals what it captures under the owner's current SM4 key, unsigned
(wrapping.Recorder: the live ROS 1 node, the ROS 2 agent, the import of recordings). A paired
robot's signature comes later, once per upload batch (provenance v2, ros_agent.batches), with
its pairing key (the SM2 key pair `python -m ros_agent pair` made, whose private key never
leaves the robot). A robot set up by hand (a key file and a token, no pairing key) never
signs, and the portal shows its records as unsigned.

`seal_record` with a signing key signs one record on its own (provenance v1, DESIGN.md
"Provenance: robots sign what they capture"): what paired agents sent before v2, which the
portal keeps verifying, kept to make such records (the benchmarks measure v1 beside v2).
"""

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ros_agent.config import AgentConfig
from smcrypto import envelope, provenance, sm2


@dataclass(frozen=True)
class RobotSigningKey:
    """A paired robot's SM2 pairing key pair."""

    private_key: str = field(repr=False)
    public_key: str  # 04||x||y

    @classmethod
    def of(cls, private_key: str) -> "RobotSigningKey":
        return cls(private_key, sm2.public_key_from_private(private_key))


def robot_signing_key(config: AgentConfig) -> RobotSigningKey | None:
    """The key a robot signs with: its pairing key, or None for a robot set up by hand."""
    return RobotSigningKey.of(config.sm2_private_key) if config.paired else None


def seal_record(
    key: bytes,
    header: Mapping[str, Any],
    plaintext: bytes,
    signing_key: RobotSigningKey | None,
) -> bytes:
    """The envelope of one record under the owner's `key`: signed on its own (v1) with
    `signing_key` when there is one (replacing a signature the header carried), else sealed
    as `header` is."""
    if signing_key is not None:
        header = provenance.sign_header(
            signing_key.private_key, signing_key.public_key, header, plaintext
        )
    return envelope.seal(key, header, plaintext)
