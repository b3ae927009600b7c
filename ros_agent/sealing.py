"""Sealing a record as this robot: the agent's one way to make an envelope.

Under the owner's current SM4 key, and for a paired robot signed with its pairing key (the SM2
key pair `python -m ros_agent pair` made, whose private key never leaves the robot): the
header gains `signer` and `sig` over the header and the plaintext (DESIGN.md "Provenance:
robots sign what they capture", smcrypto.provenance). A robot set up by hand (a key file and
a token, no pairing key) seals its records unsigned, and the portal shows them as unsigned.

Used by wrapping.Recorder (the live ROS 1 node, the ROS 2 agent, the import of recordings) and
by the uploader when it re-seals spooled envelopes under a rotated key (signed again, so that
an envelope spooled unsigned before the robot was paired leaves signed too).
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
    """The envelope of one record under the owner's `key`: signed with `signing_key` when
    there is one (replacing a signature the header carried), else sealed as `header` is."""
    if signing_key is not None:
        header = provenance.sign_header(
            signing_key.private_key, signing_key.public_key, header, plaintext
        )
    return envelope.seal(key, header, plaintext)
