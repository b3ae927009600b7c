"""python -m authros_verify: check AuthROS data without trusting the portal.

    python -m authros_verify [export] BUNDLE.json [--mcap FILE] --rpc URL [--contract 0x..]
        [--chain-id N] [--require-signed] [--complete]
    python -m authros_verify record RECORD_ID --portal URL --key-file FILE --rpc URL
        [--token-file FILE] [--contract 0x..] [--chain-id N] [--allow-unsigned]
    python -m authros_verify keys --owner 0x.. --rpc URL --contract 0x.. [--from-block N]

An export's check draws a progress bar on stderr while it runs, only when stderr is a terminal,
and ends with one verdict line on stdout: `VERIFIED: ...` or `FAILED: ...`.

Exit status: 0 everything holds; 1 a check fails (the record, key or bundle is named), or
with --complete a stream has a gap or a record is counted by none; 2 the input cannot be read,
or the chain node or the portal cannot be asked.
"""

import argparse
import json
import os
import sys
import uuid
from pathlib import Path

from eth_utils import to_checksum_address

from authros_verify.chain import ChainReader, ChainUnreachable
from authros_verify.check import Report, verify
from authros_verify.keys import RegisteredKey, robot_keys
from authros_verify.portal import (
    PortalClient,
    PortalUnusable,
    SecretUnusable,
    read_key_file,
    read_token_file,
)
from authros_verify.progress import ProgressBar, ReadCounted, bundle_records_stated
from authros_verify.record import RecordCheck, record_check

EXIT_OK, EXIT_FAILED, EXIT_UNUSABLE = 0, 1, 2
TOKEN_VARIABLE = "AUTHROS_TOKEN"  # noqa: S105 (the name of the variable, not a token)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command, arguments = (argv[0], argv[1:]) if argv[:1] in (["record"], ["keys"]) else ("", argv)
    if command == "record":
        return record_main(arguments)
    if command == "keys":
        return keys_main(arguments)
    return export_main(arguments[1:] if arguments[:1] == ["export"] else arguments)


# --- an export -----------------------------------------------------------------------------


def export_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m authros_verify [export]",
        description="Check an AuthROS export's proof bundle (and its MCAP file) against the "
        "chain, and each record's robot signature over the exported content.",
        epilog="Also: `python -m authros_verify record --help` (one record, from the portal) "
        "and `python -m authros_verify keys --help` (an owner's robot keys on chain).",
    )
    parser.add_argument("bundle", type=Path, help="the proof bundle (.json)")
    parser.add_argument("--mcap", type=Path, help="the exported MCAP file, to check it too")
    parser.add_argument("--rpc", required=True, help="a JSON-RPC URL of a node of the chain")
    parser.add_argument("--contract", help="the AuthROS contract you expect (0x address)")
    parser.add_argument("--chain-id", type=int, help="the chain id you expect")
    parser.add_argument(
        "--require-signed",
        action="store_true",
        help="fail unless every record is genuine (signed by its owner's robot)",
    )
    parser.add_argument(
        "--complete",
        action="store_true",
        help="fail on any gap in any stream, whatever reason the portal gives (a reason is "
        "its word, not signed), and on any record no stream counts (unsigned or v1)",
    )
    parser.add_argument(
        "--jobs",
        type=int,
        default=0,
        metavar="N",
        help="check the records in N processes (0, the default: one per core); the report is "
        "the same",
    )
    args = parser.parse_args(argv)
    if args.jobs < 0:
        parser.error("--jobs must be 0 or more")
    chain = ChainReader.from_url(args.rpc)
    bar = ProgressBar(sys.stderr)
    try:
        for given in (args.bundle, args.mcap):
            if given is not None and not given.is_file():
                raise OSError(f"{given} is not a file")
        report = _export_checked(args, chain, bar)
        chain_id = args.chain_id if args.chain_id is not None else chain.chain_id()
    except OSError as exc:
        print(f"cannot read: {exc}", file=sys.stderr)
        return EXIT_UNUSABLE
    except ChainUnreachable as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_UNUSABLE
    finally:
        bar.close()
    print_report(report, mcap_checked=args.mcap is not None, pinned=args.contract is not None)
    failure = export_failure(report, require_signed=args.require_signed, complete=args.complete)
    print(failure or verified_line(report, chain_id=chain_id, contract=args.contract))
    return EXIT_FAILED if failure else EXIT_OK


def _export_checked(args: argparse.Namespace, chain: ChainReader, bar: ProgressBar) -> Report:
    """The export checked, the bar following the MCAP file's bytes, then the records."""
    total = bundle_records_stated(args.bundle) if bar.shown else 0

    def records_checked(done: int) -> None:
        bar.show("records  ", done, total)

    checked = {
        "chain": chain,
        "contract": args.contract,
        "chain_id": args.chain_id,
        "jobs": args.jobs or os.cpu_count() or 1,
        "progress": records_checked if bar.shown else None,
    }
    if args.mcap is None or not bar.shown:  # nothing drawn: the file as given, unwrapped
        return verify(args.bundle, mcap=args.mcap, **checked)
    with args.mcap.open("rb") as source:
        # read twice: its SM3 and size, then its messages
        mcap = ReadCounted(source, bar, stage="MCAP file", passes=2)
        return verify(args.bundle, mcap=mcap, **checked)


def export_failure(report: Report, *, require_signed: bool, complete: bool) -> str:
    """The verdict line of an export that fails, or "" when it holds."""
    if not report.ok:
        return (
            f"FAILED: {len(report.failed):,} of {len(report.records):,} records refused, "
            f"{len(report.problems)} problems with the bundle or the MCAP file"
        )
    if require_signed and report.not_genuine:
        return f"FAILED: {len(report.not_genuine)} records are not genuine (--require-signed)"
    if complete and (report.gaps or report.uncounted):
        return (
            f"FAILED: {report.gaps} gaps, {len(report.uncounted)} records no stream counts "
            "(--complete)"
        )
    return ""


def verified_line(report: Report, *, chain_id: int, contract: str | None) -> str:
    """The verdict line of an export that holds: its records, the chain and the contract."""
    pinned = contract if contract is not None else "named by the bundle (not pinned)"
    unsigned = len(report.not_genuine)
    but = f", {unsigned:,} unsigned (not genuine)" if unsigned else ""
    return (
        f"VERIFIED: {len(report.records):,} records, {len(report.failed)} refused{but}, "
        f"chain {chain_id} contract {pinned}"
    )


def print_report(report: Report, *, mcap_checked: bool, pinned: bool) -> None:
    for result in report.failed:
        print(f"FAIL record {result.record} (#{result.index}): {'; '.join(result.problems)}")
    for problem in report.problems:
        print(f"FAIL bundle: {problem}")
    for result in report.not_genuine:
        why = (
            "its anchored envelope carries no robot signature: anchored, but no robot vouches "
            "for its content (the portal's word)"
        )
        print(f"UNSIGNED record {result.record} (#{result.index}): {why}")
    good = len(report.records) - len(report.failed)
    print(
        f"{good} of {len(report.records)} records verified against the chain: "
        f"{len(report.genuine)} genuine (signed by a robot key their owner registered), "
        f"{len(report.not_genuine)} unsigned; {report.signatures_verified} SM2 verifications "
        "(one per upload batch)"
    )
    print_streams(report)
    if not mcap_checked:
        print("note: no --mcap given; the MCAP file itself was not checked")
    if not pinned:
        print("note: no --contract given; the contract the bundle names was trusted")


def print_streams(report: Report) -> None:
    """Per stream (signer, topic) of the records that hold: first, last, count and each gap,
    numbered by the topic_seq each robot signed."""
    for stream in report.streams:
        span = "none" if stream.first is None else f"{stream.first}..{stream.last}"
        state = "nothing missing" if not stream.gaps else f"{len(stream.gaps)} gaps"
        print(
            f"stream signer {stream.signer} topic {stream.topic} (robot {stream.robot}): "
            f"topic_seq {span}, {stream.count} records, {state}"
        )
        for gap in stream.gaps:
            numbers = f"{gap.start}" if gap.start == gap.end else f"{gap.start}..{gap.end}"
            detail = f" ({gap.detail})" if gap.detail else ""
            print(f"    GAP {numbers} ({gap.size} records): {gap.reason}{detail}")
    if report.uncounted:
        print(
            f"note: {len(report.uncounted)} records carry no signed topic_seq (unsigned or "
            "provenance v1): no stream counts them"
        )


# --- one record, from the portal -------------------------------------------------------------


def record_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m authros_verify record",
        description="Fetch one record's content and proof from the portal with an owner API "
        "token, decrypt it with your own SM4 key, check it against the chain and print its "
        "plaintext (on stdout) only when every check holds.",
    )
    parser.add_argument("record", help="the record id (UUID)")
    parser.add_argument("--portal", required=True, help="the portal's URL (https://...)")
    parser.add_argument(
        "--key-file", required=True, type=Path, help="your SM4 key, 32 hex digits (mode 0600)"
    )
    parser.add_argument(
        "--token-file",
        type=Path,
        help=f"your owner API token (`read` scope), mode 0600; else ${TOKEN_VARIABLE}",
    )
    parser.add_argument("--rpc", required=True, help="a JSON-RPC URL of a node you trust")
    parser.add_argument("--contract", help="the AuthROS contract you expect (0x address)")
    parser.add_argument("--chain-id", type=int, help="the chain id you expect")
    parser.add_argument(
        "--allow-unsigned",
        action="store_true",
        help="print an unsigned record's plaintext too (it is never genuine)",
    )
    args = parser.parse_args(argv)
    try:
        record = uuid.UUID(args.record)
    except ValueError:
        print(f"not a record id: {args.record!r}", file=sys.stderr)
        return EXIT_UNUSABLE
    try:
        key = read_key_file(args.key_file)
        token = (
            read_token_file(args.token_file)
            if args.token_file
            else os.environ.get(TOKEN_VARIABLE, "")
        )
        if not token:
            raise SecretUnusable(f"give --token-file or set {TOKEN_VARIABLE}")
        content, proof = PortalClient(args.portal, token).record_answers(record)
        checked = record_check(
            record=str(record),
            content=content,
            proof=proof,
            key=key,
            chain=ChainReader.from_url(args.rpc),
            contract=args.contract,
            chain_id=args.chain_id,
            allow_unsigned=args.allow_unsigned,
        )
    except (SecretUnusable, PortalUnusable, ChainUnreachable) as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_UNUSABLE
    print_record_check(checked)
    if checked.plaintext is None:
        return EXIT_FAILED
    sys.stdout.buffer.write(checked.plaintext)
    sys.stdout.flush()
    return EXIT_OK


def print_record_check(checked: RecordCheck) -> None:
    """Each check and its outcome, on stderr (stdout is the plaintext's)."""
    marks = {True: "ok  ", False: "FAIL", None: "--  "}
    for outcome in checked.outcomes:
        print(f"{marks[outcome.holds]} {outcome.check}: {outcome.detail}", file=sys.stderr)
    if checked.failed:
        names = ", ".join(outcome.check for outcome in checked.failed)
        print(f"FAILED record {checked.record}: {names}", file=sys.stderr)
    elif checked.genuine:
        print(f"OK record {checked.record}: genuine", file=sys.stderr)
    else:
        print(f"OK record {checked.record}: unsigned, not genuine", file=sys.stderr)


# --- an owner's robot keys -------------------------------------------------------------------


def keys_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m authros_verify keys",
        description="List every robot key ever registered for an owner, from chain events "
        "alone, so that the owner can notice a key it never paired.",
    )
    parser.add_argument("--owner", required=True, help="the owner's EOA (0x address)")
    parser.add_argument("--rpc", required=True, help="a JSON-RPC URL of a node you trust")
    parser.add_argument("--contract", required=True, help="the AuthROS contract (0x address)")
    parser.add_argument("--from-block", type=int, default=0, help="the first block to read")
    parser.add_argument("--json", action="store_true", help="print the keys as JSON")
    args = parser.parse_args(argv)
    try:
        owner, contract = to_checksum_address(args.owner), to_checksum_address(args.contract)
    except ValueError as exc:
        print(f"not an address: {exc}", file=sys.stderr)
        return EXIT_UNUSABLE
    chain = ChainReader.from_url(args.rpc)
    try:
        if not chain.has_code(contract):
            print(f"there is no contract at {contract} on this chain", file=sys.stderr)
            return EXIT_UNUSABLE
        keys = robot_keys(chain, contract=contract, owner=owner, from_block=args.from_block)
    except ChainUnreachable as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_UNUSABLE
    if args.json:
        print(json.dumps([_key_json(key) for key in keys], indent=2))
    else:
        print_keys(keys, owner=owner, contract=contract)
    return EXIT_OK if all(key.hash_holds for key in keys) else EXIT_FAILED


def _key_json(key: RegisteredKey) -> dict[str, object]:
    return {
        "key_hash": "0x" + key.key_hash.hex(),
        "public_key": key.public_key_hex,
        "fingerprint": key.fingerprint,
        "hash_holds": key.hash_holds,
        "added_block": key.added_block,
        "added_tx": key.added_tx,
        "revoked_block": key.revoked_block,
        "revoked_tx": key.revoked_tx,
    }


def print_keys(keys: list[RegisteredKey], *, owner: str, contract: str) -> None:
    print(f"robot keys registered on chain by {owner} (contract {contract}), from its events:")
    for key in keys:
        added = f"added in block {key.added_block}" if key.added_block is not None else ""
        state = f"revoked in block {key.revoked_block}" if key.revoked_block is not None else "live"
        print(f"key 0x{key.key_hash.hex()}  {added}  {state}")
        print(f"    public key {key.public_key_hex}  fingerprint {key.fingerprint}")
        if not key.hash_holds:
            print("    MISMATCH: this public key does not hash (SM3) to the key hash")
    live = sum(key.revoked_block is None for key in keys)
    print(f"{len(keys)} robot keys, {live} live")
    print(
        "note: compare them with the robots you paired (the portal shows each key's "
        "fingerprint); a key you never paired was registered by whoever holds your account"
    )


if __name__ == "__main__":
    sys.exit(main())
