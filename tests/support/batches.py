"""Envelopes of one upload batch signed once, as a paired robot's agent signs them (DESIGN.md
"Provenance v2"): `batch_signed` gives the headers and plaintexts (to change one before it is
sealed, as an attacker holding the owner's key could), `batch_sealed` seals them under the
owner's key, `seal_batch` does both."""

import json
from collections.abc import Sequence
from datetime import UTC, datetime

from smcrypto import envelope, provenance
from tests.support.robot_setup import RobotSetup


def batch_signed(
    setup: RobotSetup,
    seqs: Sequence[int],
    *,
    topic_seqs: Sequence[int] | None = None,
    topic: str = "/robot/odom",
    data_type: str = "nav_msgs/Odometry",
) -> list[tuple[dict, bytes]]:
    """The (header, plaintext) of records under upload seqs `seqs` and topic_seqs (by default
    the upload seqs), signed as one batch with the robot's pairing key."""
    topic_seqs = list(seqs) if topic_seqs is None else list(topic_seqs)
    now = datetime.now(tz=UTC).isoformat().replace("+00:00", "Z")
    records = [
        (
            {
                "owner": setup.owner.username,
                "robot": str(setup.robot.id),
                "topic": topic,
                "type": data_type,
                "seq": seq,
                "time": now,
                "topic_seq": topic_seq,
            },
            json.dumps({"K": {"seq": seq, "topic_seq": topic_seq}}).encode(),
        )
        for seq, topic_seq in zip(seqs, topic_seqs, strict=True)
    ]
    headers = provenance.sign_batch(*setup.signing_key, records)
    return [(header, body) for header, (_, body) in zip(headers, records, strict=True)]


def batch_sealed(setup: RobotSetup, signed: Sequence[tuple[dict, bytes]]) -> list[bytes]:
    """Each (header, plaintext) sealed under the owner's key, as the agent seals."""
    return [envelope.seal(setup.key, header, body) for header, body in signed]


def seal_batch(setup: RobotSetup, seqs: Sequence[int], **kwargs: object) -> list[bytes]:
    """The envelopes of one batch signed once (see batch_signed)."""
    return batch_sealed(setup, batch_signed(setup, seqs, **kwargs))
