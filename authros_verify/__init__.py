"""A standalone check of an AuthROS export's proof bundle (and its MCAP file) against the chain.

    python -m authros_verify BUNDLE.json [--mcap FILE] --rpc URL [--contract 0x..] [--chain-id N]

No Django and nothing of the portal: SM3 and the Merkle fold come from `smcrypto`, the chain
from web3. docs/export.md describes the bundle and what is checked.
"""

from authros_verify.bundle import (
    BUNDLE_FORMAT,
    bundle_digest,
    bundle_serialise,
    record_line_index,
)
from authros_verify.chain import ChainReader, ChainUnreachable
from authros_verify.check import RecordResult, Report, verify

__all__ = [
    "BUNDLE_FORMAT",
    "ChainReader",
    "ChainUnreachable",
    "RecordResult",
    "Report",
    "bundle_digest",
    "bundle_serialise",
    "record_line_index",
    "verify",
]
