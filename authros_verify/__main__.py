"""python -m authros_verify BUNDLE.json [--mcap FILE] --rpc URL [--contract 0x..] [--chain-id N]

Exit status: 0 every record holds; 1 a record (named) or the bundle fails; 2 the input cannot
be read or the chain node cannot be asked.
"""

import argparse
import sys
from pathlib import Path

from authros_verify.chain import ChainReader, ChainUnreachable
from authros_verify.check import Report, verify

EXIT_OK, EXIT_FAILED, EXIT_UNUSABLE = 0, 1, 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m authros_verify",
        description="Check an AuthROS export's proof bundle (and its MCAP file) against the chain.",
    )
    parser.add_argument("bundle", type=Path, help="the proof bundle (.json)")
    parser.add_argument("--mcap", type=Path, help="the exported MCAP file, to check it too")
    parser.add_argument("--rpc", required=True, help="a JSON-RPC URL of a node of the chain")
    parser.add_argument("--contract", help="the AuthROS contract you expect (0x address)")
    parser.add_argument("--chain-id", type=int, help="the chain id you expect")
    args = parser.parse_args(argv)
    try:
        bundle = args.bundle.read_bytes()
        mcap = args.mcap.read_bytes() if args.mcap else None
    except OSError as exc:
        print(f"cannot read: {exc}", file=sys.stderr)
        return EXIT_UNUSABLE
    try:
        report = verify(
            bundle,
            chain=ChainReader.from_url(args.rpc),
            mcap=mcap,
            contract=args.contract,
            chain_id=args.chain_id,
        )
    except ChainUnreachable as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_UNUSABLE
    print_report(report, mcap_checked=mcap is not None, pinned=args.contract is not None)
    return EXIT_OK if report.ok else EXIT_FAILED


def print_report(report: Report, *, mcap_checked: bool, pinned: bool) -> None:
    for result in report.failed:
        print(f"FAIL record {result.record} (#{result.index}): {'; '.join(result.problems)}")
    for problem in report.problems:
        print(f"FAIL bundle: {problem}")
    good = len(report.records) - len(report.failed)
    print(f"{good} of {len(report.records)} records verified against the chain")
    if not mcap_checked:
        print("note: no --mcap given; the MCAP file itself was not checked")
    if not pinned:
        print("note: no --contract given; the contract the bundle names was trusted")
    print("OK" if report.ok else "FAILED")


if __name__ == "__main__":
    sys.exit(main())
