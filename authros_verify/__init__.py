"""Check AuthROS data against the chain without trusting the portal.

    python -m authros_verify [export] BUNDLE.json [--mcap FILE] --rpc URL [--contract 0x..]
        [--complete]
    python -m authros_verify record RECORD_ID --portal URL --key-file FILE --rpc URL ...
    python -m authros_verify keys --owner 0x.. --rpc URL --contract 0x..

An export's bundle and MCAP file (check.py), its records counted per stream (streams.py),
one record as the portal serves it (record.py), and the robot keys an owner's EOA registered
(keys.py). No Django and nothing of the portal:
SM2/SM3/SM4, envelopes, signatures and the Merkle fold come from `smcrypto`, the chain from
web3, and the MCAP messages a signed plaintext makes from rosbags (messages.py).
docs/export.md describes the bundle and every check.
"""

from authros_verify.bundle import (
    BUNDLE_FORMAT,
    BUNDLE_FORMAT_V1,
    BUNDLE_FORMAT_V2,
    bundle_digest,
    bundle_serialise,
    record_line_index,
)
from authros_verify.chain import ChainReader, ChainUnreachable
from authros_verify.check import RecordResult, Report, verify
from authros_verify.keys import RegisteredKey, robot_keys
from authros_verify.record import RecordCheck, record_check
from authros_verify.streams import Gap, StreamReport

__all__ = [
    "BUNDLE_FORMAT",
    "BUNDLE_FORMAT_V1",
    "BUNDLE_FORMAT_V2",
    "ChainReader",
    "ChainUnreachable",
    "Gap",
    "RecordCheck",
    "RecordResult",
    "RegisteredKey",
    "Report",
    "StreamReport",
    "bundle_digest",
    "bundle_serialise",
    "record_check",
    "record_line_index",
    "robot_keys",
    "verify",
]
