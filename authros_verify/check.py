"""The check of a proof bundle: every record's envelope, proof and anchor against the chain,
its robot's signature over its plaintext, and its MCAP message against the file and against
the message its signed plaintext makes; the bundle's own form and digest.

A record fails if anything about it does not hold; the bundle fails if any record does, or
if something outside the records (its form, digest, chain, contract, MCAP file) does not. A
record that holds is genuine when its robot signed it, else unsigned (docs/export.md).

Whether a record is signed, and v1 or v2, is read from its anchored envelope's header (which
the chain anchors through its digest), never from the bundle's format or fields: a signed
record in a bundle that carries no signatures (relabelled to an older format) fails, it is
not passed as unsigned. The records that hold are counted per stream by their signed
`topic_seq` (authros_verify/streams.py); the MCAP file is read as a stream (mcapfile.py).
"""

import io
import json
import multiprocessing
import re
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from authros_verify.anchor import anchor_check
from authros_verify.bundle import (
    BUNDLE_FORMAT,
    BUNDLE_FORMAT_V1,
    BUNDLE_FORMAT_V2,
    bundle_digest,
    bundle_entry_line,
    bundle_serialise,
    record_line_index,
)
from authros_verify.chain import ChainReader
from authros_verify.mcapfile import McapUnreadable, mcap_messages
from authros_verify.messages import (
    EncodedMessage,
    message_encode,
    message_log_time,
    ros2_type_name,
    schema_of,
)
from authros_verify.signature import Signatures, is_signed, robot_key_check, signature_check
from authros_verify.streams import StreamReport, StreamsMalformed, StreamTally
from authros_verify.values import Invalid, address, base64_bytes, hash32, micros, whole
from smcrypto.envelope import BATCH_FIELDS, EnvelopeInfo, read_header
from smcrypto.errors import CryptoError
from smcrypto.sm3 import sm3_digest, sm3_hasher, sm3_hex

# The fields of a record's entry in a v1 bundle (exports made before records were signed).
RECORD_FIELDS_V1 = {
    "record",
    "owner",
    "digest",
    "mode",
    "leaf_index",
    "tree_size",
    "path",
    "root",
    "anchor",
    "robot",
    "topic",
    "type",
    "seq",
    "captured_at",
    "envelope",
    "mcap",
}
# v2 adds the robot's signature (null: unsigned) and the plaintext it signed (null: unsigned).
RECORD_FIELDS_V2 = RECORD_FIELDS_V1 | {"signature", "plaintext"}
# v3 adds the record's topic_seq and its place in its upload batch (both null but for
# provenance v2), as its anchored envelope's header states them.
RECORD_FIELDS = RECORD_FIELDS_V2 | {"topic_seq", "batch"}
RECORD_FIELDS_OF = {
    BUNDLE_FORMAT: RECORD_FIELDS,
    BUNDLE_FORMAT_V2: RECORD_FIELDS_V2,
    BUNDLE_FORMAT_V1: RECORD_FIELDS_V1,
}
SIGNATURE_FIELDS = {"signer", "sig", "public_key"}
MCAP_FIELDS = {
    "topic",
    "sequence",
    "log_time",
    "publish_time",
    "message_encoding",
    "schema",
    "sm3",
}
BUNDLE_FIELDS_V2 = {
    "format",
    "export",
    "created_at",
    "requested_by",
    "selection",
    "chain_id",
    "contract",
    "mcap",
    "records",
    "excluded",
    "bundle_sm3",
}
# v3 adds the portal's completeness of the selection (sharing.selectors.completeness).
BUNDLE_FIELDS = BUNDLE_FIELDS_V2 | {"streams"}
BUNDLE_FIELDS_OF = {
    BUNDLE_FORMAT: BUNDLE_FIELDS,
    BUNDLE_FORMAT_V2: BUNDLE_FIELDS_V2,
    BUNDLE_FORMAT_V1: BUNDLE_FIELDS_V2,
}


@dataclass(slots=True)
class RecordResult:
    index: int
    record: str  # the record id as the bundle states it
    problems: list[str] = field(default_factory=list)
    # True: its robot's signature holds (genuine); False: its envelope is unsigned; None: not
    # known (it failed first).
    signed: bool | None = None

    topic_seq: int | None = None  # its signed number in its stream, once it holds

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def genuine(self) -> bool:
        return self.ok and self.signed is True


@dataclass
class Report:
    problems: list[str] = field(default_factory=list)  # about the bundle as a whole
    records: list[RecordResult] = field(default_factory=list)
    # Per (signer, topic) of the records that hold: first, last, count and gaps.
    streams: list[StreamReport] = field(default_factory=list)
    signatures_verified: int = 0  # SM2 verifications made (one per v2 batch)

    @property
    def gaps(self) -> int:
        return sum(len(stream.gaps) for stream in self.streams)

    @property
    def uncounted(self) -> list[RecordResult]:
        """Records that hold but no stream counts (unsigned, or signed without topic_seq)."""
        return [result for result in self.records if result.ok and result.topic_seq is None]

    @property
    def failed(self) -> list[RecordResult]:
        return [result for result in self.records if not result.ok]

    @property
    def ok(self) -> bool:
        return not self.problems and bool(self.records) and not self.failed

    @property
    def genuine(self) -> list[RecordResult]:
        return [result for result in self.records if result.genuine]

    @property
    def not_genuine(self) -> list[RecordResult]:
        """Records that hold but whose content no robot signature vouches for."""
        return [result for result in self.records if result.ok and not result.genuine]


def verify(
    bundle: bytes | Path,
    *,
    chain: ChainReader,
    mcap: bytes | Path | IO[bytes] | None = None,
    contract: str | None = None,
    chain_id: int | None = None,
    jobs: int = 1,
    progress: Callable[[int], None] | None = None,
) -> Report:
    """Check the bundle (its bytes, or its path) and the MCAP file, if given (its bytes, its
    path, or a binary file at its start), against the chain.

    A bundle in its canonical form (every line its own, as the portal writes it) is read line
    by line, once: its head, then each record's line checked (its form, then the record) as
    its bytes are hashed for `bundle_sm3`, never held whole; one that is not is read whole, so
    that the record whose line changed is named. With `jobs` above 1 the records' lines are
    checked by that many forked processes, the lines of one upload batch together (so that
    its signature is still verified once), their results gathered in order: the same report
    as one process's. The MCAP file is read as a stream (`_mcap_messages`). `contract` and
    `chain_id` are what the verifier knows independently (the portal's published contract);
    without them the bundle's own are checked for consistency only. `progress`, if given, is
    told how many records are checked so far after each chunk of them (a progress bar's; the
    report is the same). Raises ChainUnreachable if the node cannot be asked; OSError if a
    file cannot be read.
    """
    with _lines_of(bundle) as lines:
        head = _head_read(lines)
        if head is None:
            return _verify_whole(
                _bytes_of(bundle), chain=chain, mcap=mcap, contract=contract, chain_id=chain_id
            )
        report = Report()
        _check_fields(report, head)
        checker = _RecordChecker(
            head=_check_head(report, head, chain, contract, chain_id),
            chain=chain,
            messages=_mcap_messages(report, head, mcap),
            fields=RECORD_FIELDS_OF.get(head.get("format"), RECORD_FIELDS),
        )
        kept = _Kept(report)
        scan = _Scan(head)
        for outcomes, verified in _chunks_checked(checker, scan.chunks(lines), jobs):
            for outcome in outcomes:
                if outcome is None:  # a line not in its canonical form
                    scan.canonical = False
                    break
                kept.add(outcome)
            report.signatures_verified += verified
            if not scan.canonical:
                break
            if progress is not None:
                progress(len(report.records))
    if not scan.canonical:
        return _verify_whole(
            _bytes_of(bundle), chain=chain, mcap=mcap, contract=contract, chain_id=chain_id
        )
    if head.get("bundle_sm3") != scan.digest():
        report.problems.insert(0, "the bundle's digest (bundle_sm3) does not match its content")
    kept.finish(head, checker.messages)
    return report


def _bytes_of(bundle: bytes | Path) -> bytes:
    return bundle if isinstance(bundle, bytes | bytearray) else bundle.read_bytes()


def _verify_whole(
    bundle: bytes,
    *,
    chain: ChainReader,
    mcap: bytes | Path | IO[bytes] | None,
    contract: str | None,
    chain_id: int | None,
) -> Report:
    """The check of a bundle read whole: one that is not in its canonical form line by line
    (a changed byte, even one that breaks the JSON, is traced to the record on its line)."""
    report = Report()
    try:
        document = _strict_json(bundle)
    except (UnicodeDecodeError, ValueError) as exc:
        report.problems.append(f"the bundle is not valid JSON: {exc}")
        _name_broken_line(report, bundle, exc)
        return report
    if not isinstance(document, dict) or not isinstance(document.get("records"), list):
        report.problems.append("the bundle is not an object with a list of records")
        return report
    entries = document["records"]
    report.records = [
        RecordResult(i, str(entry.get("record")) if isinstance(entry, dict) else "?")
        for i, entry in enumerate(entries)
    ]
    _check_form(report, bundle, document)
    checker = _RecordChecker(
        head=_check_head(report, document, chain, contract, chain_id),
        chain=chain,
        messages=_mcap_messages(report, document, mcap),
        fields=RECORD_FIELDS_OF.get(document.get("format"), RECORD_FIELDS),
    )
    named = {result.index: result.problems for result in report.records if result.problems}
    kept = _Kept(report)
    for index, entry in enumerate(entries):
        outcome = checker.outcome(index, entry)
        outcome.problems[:0] = named.get(index, [])
        kept.add(outcome)
    report.signatures_verified = checker.signatures.verified
    kept.finish(document, checker.messages)
    return report


@dataclass(slots=True)
class _Outcome:
    """What checking one record's entry found, handed from the process that checked it."""

    index: int
    record: str
    problems: list[str]
    signed: bool | None
    stream: tuple[str, str, str, int] | None  # (signer, topic, robot, topic_seq)
    sequence: int | None  # the MCAP sequence its entry names, if it is a whole number


@dataclass
class _RecordChecker:
    """Each record's check against what the whole bundle shares: its head, the chain, the
    MCAP file's messages, the format's fields and the SM2 verifications made so far."""

    head: "_Head"
    chain: ChainReader
    messages: dict | None
    fields: set[str]
    signatures: Signatures = field(default_factory=Signatures)

    def outcome(self, index: int, entry: Any) -> _Outcome:
        problems: list[str] = []
        signed = stream = None
        try:
            counted = _check_record(
                entry, self.head, self.chain, self.messages, self.fields, self.signatures
            )
            signed, stream = counted.signed, counted.stream
        except Invalid as exc:
            problems.append(str(exc))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            problems.append(f"its entry is malformed ({type(exc).__name__}: {exc})")
        record = str(entry.get("record")) if isinstance(entry, dict) else "?"
        sequence = entry["mcap"]["sequence"] if _has_sequence(entry) else None
        return _Outcome(index, record, problems, signed, stream, sequence)

    def lines_checked(self, chunk: "_Chunk") -> tuple[list[_Outcome | None], int]:
        """Each line of the chunk checked to be its record's one serialisation, then its
        record checked (None for a line that is not: the bundle is then read whole); and how
        many SM2 verifications that took."""
        before = self.signatures.verified
        outcomes: list[_Outcome | None] = []
        for index, line in enumerate(chunk.lines, start=chunk.first):
            try:
                entry = _canonical_entry(line)
            except (UnicodeDecodeError, ValueError):
                entry = None
            if entry is None:
                outcomes.append(None)
                break
            outcomes.append(self.outcome(index, entry))
        return outcomes, self.signatures.verified - before


class _Kept:
    """What the check keeps of each record once checked, so kept small: its result, the first
    record naming each MCAP sequence (all of them only for a sequence named twice), and each
    counted record's stream (one tuple per stream, shared) and number."""

    def __init__(self, report: Report) -> None:
        self.report = report
        report.records = []
        self.sequences: dict[int, RecordResult] = {}
        self.shared: dict[int, list[RecordResult]] = {}
        self.streams: dict[tuple[str, str, str], tuple[str, str, str]] = {}
        self.numbered: list[tuple[RecordResult, tuple[str, str, str], int]] = []

    def add(self, outcome: _Outcome) -> None:
        result = RecordResult(outcome.index, outcome.record, outcome.problems, outcome.signed)
        self.report.records.append(result)
        if outcome.stream is not None:
            *key, number = outcome.stream
            key = tuple(key)
            self.numbered.append((result, self.streams.setdefault(key, key), number))
        if outcome.sequence is not None:
            first = self.sequences.setdefault(outcome.sequence, result)
            if first is not result:
                self.shared.setdefault(outcome.sequence, [first]).append(result)

    def finish(self, document: dict, messages: dict | None) -> None:
        """Name the MCAP sequences two records claim, count the records that hold in their
        streams, and name the MCAP messages no record names."""
        report = self.report
        _name_shared_sequences(self.shared)
        tally = StreamTally()
        for result, stream, number in self.numbered:
            if result.ok:
                _count(tally, result, (*stream, number))
        try:
            excluded = document.get("excluded")
            report.streams = tally.reports(
                document.get("streams"), excluded if isinstance(excluded, list) else []
            )
        except StreamsMalformed as exc:
            report.problems.append(f"the bundle's streams (the portal's completeness): {exc}")
            report.streams = tally.reports(None, [])
        if messages is not None:
            extra = sorted(set(messages) - set(self.sequences))
            if extra:
                report.problems.append(f"the MCAP file has messages no record names: {extra[:5]}")


# --- records checked in forked processes ------------------------------------------------------

# Lines handed to a process at a time, at least (a chunk ends where an upload batch does).
CHUNK_LINES = 256
_SIG_FIELD = b'"sig":"'
_FORKED: _RecordChecker | None = None  # the check a forked process runs (set before forking)


@dataclass(frozen=True)
class _Chunk:
    first: int  # the index of its first record
    lines: list[bytes]  # each record's line, without its comma and line break


def _chunks_checked(
    checker: _RecordChecker, chunks: Iterator[_Chunk], jobs: int
) -> Iterator[tuple[list[_Outcome | None], int]]:
    """Each chunk's outcomes in order, checked here (jobs 1, or where processes cannot be
    forked) or by `jobs` forked processes, each with the chain reader of its own."""
    if jobs <= 1 or "fork" not in multiprocessing.get_all_start_methods():
        yield from map(checker.lines_checked, chunks)
        return
    global _FORKED
    _FORKED = checker
    try:
        context = multiprocessing.get_context("fork")
        with context.Pool(jobs, initializer=_forked_start) as pool:
            # At most two chunks a process in flight: the bundle is never read ahead whole.
            waiting: deque = deque()
            for chunk in chunks:
                waiting.append(pool.apply_async(_forked_lines_checked, (chunk,)))
                if len(waiting) >= 2 * jobs:
                    yield waiting.popleft().get()
            while waiting:
                yield waiting.popleft().get()
    finally:
        _FORKED = None


def _forked_start() -> None:
    _FORKED.chain = _FORKED.chain.forked()


def _forked_lines_checked(chunk: _Chunk) -> tuple[list[_Outcome | None], int]:
    return _FORKED.lines_checked(chunk)


# --- the bundle read line by line ------------------------------------------------------------


@contextmanager
def _lines_of(bundle: bytes | Path) -> Iterator[Iterator[bytes]]:
    """The bundle's lines, each with its line break (the last one without, if the bundle
    does not end with one), read from its bytes or its file."""
    if isinstance(bundle, bytes | bytearray):
        yield iter(io.BytesIO(bundle))
        return
    with bundle.open("rb") as source:
        yield iter(source)


def _head_read(lines: Iterator[bytes]) -> dict | None:
    """The head (every top-level field but `records`) of a bundle whose first two lines are
    in their canonical form (bundle_serialise's); None if they are not."""
    try:
        first = _unbroken(next(lines))
        head = _strict_json(first[:-1] + b"}") if first.endswith(b",") else None
        if not isinstance(head, dict) or "records" in head:
            return None
        if (bundle_entry_line(head)[:-1] + ",").encode("ascii") != first:
            return None
        if _unbroken(next(lines)) != b'"records":[':
            return None
    except (StopIteration, UnicodeDecodeError, ValueError, _NotCanonical):
        return None
    return head


def _batch_hint(line: bytes) -> bytes | None:
    """The batch signature a record's line states (its `"sig":"` field, last in the line's
    sorted fields but `topic_seq` and `type`), or None: where to cut chunks, never trusted.
    A search from the end, not a pattern over the whole line (5 KB of base64 before it)."""
    at = line.rfind(_SIG_FIELD)
    return None if at < 0 else line[at + len(_SIG_FIELD) : at + len(_SIG_FIELD) + 128]


class _Scan:
    """The record lines of a bundle read once after its head, cut into chunks (an upload
    batch's lines kept together), hashed as they go by for `bundle_sm3`; `canonical` turns
    False when a line is not where the bundle's serialisation puts it (then the bundle is read
    whole to name it)."""

    def __init__(self, head: dict) -> None:
        self.canonical = True
        self._body = {name: value for name, value in head.items() if name != "bundle_sm3"}
        names = sorted([*self._body, "records"])
        self._after = names[names.index("records") + 1 :]
        self._hasher = sm3_hasher()
        self._hasher.update(b"{")
        for position, name in enumerate(names[: names.index("records")]):
            self._hasher.update(
                (("," if position else "") + _field(name, self._body[name])).encode("ascii")
            )
        self._hasher.update(("," if names[0] != "records" else "").encode("ascii") + b'"records":[')
        self._closed = False

    def chunks(self, lines: Iterator[bytes]) -> Iterator[_Chunk]:
        """The record lines (after the head and `"records":[`, which _head_read took, before
        `]}`), without their commas, CHUNK_LINES or more at a time, cut where the next line
        states another batch signature than the last (a scheduling hint, never trusted: a
        cut elsewhere only costs one more SM2 verification), or at 8 * CHUNK_LINES."""
        hasher, count = self._hasher, 0
        pending: bytes | None = None  # a line is known to be the last at the next line
        chunk: list[bytes] = []
        last_sig: bytes | None = None
        try:
            for raw in lines:
                line = _unbroken(raw)
                if line == b"]}":
                    self._closed = True
                    break
                if pending is not None:
                    if not pending.endswith(b","):
                        raise _NotCanonical
                    text = pending[:-1]
                    hasher.update(text if count == 0 else b"," + text)
                    count += 1
                    sig = _batch_hint(text)
                    if len(chunk) >= 8 * CHUNK_LINES or (
                        len(chunk) >= CHUNK_LINES and sig != last_sig
                    ):
                        yield _Chunk(count - 1 - len(chunk), chunk)
                        chunk = []
                    chunk.append(text)
                    last_sig = sig
                pending = line
            if not self._closed or next(lines, None) is not None:
                raise _NotCanonical  # no closing line, or lines after it
            if pending is not None:
                if pending.endswith(b","):
                    raise _NotCanonical
                hasher.update(pending if count == 0 else b"," + pending)
                count += 1
                chunk.append(pending)
            if chunk:
                yield _Chunk(count - len(chunk), chunk)
        except _NotCanonical:
            self.canonical = False

    def digest(self) -> str:
        """`0x` + SM3 of the bundle's compact JSON without `bundle_sm3`, once every line was
        read."""
        self._hasher.update(b"]")
        for name in self._after:
            self._hasher.update(("," + _field(name, self._body[name])).encode("ascii"))
        self._hasher.update(b"}")
        return "0x" + self._hasher.finalize().hex()


class _NotCanonical(Exception):
    """A line is not the one the bundle's serialisation makes."""


def _unbroken(line: bytes) -> bytes:
    """A line without its line break; every line of a bundle has one."""
    if not line.endswith(b"\n"):
        raise _NotCanonical
    return line[:-1]


def _field(name: str, value: Any) -> str:
    return bundle_entry_line({name: value})[1:-1]


# --- the bundle as a whole -------------------------------------------------------------------


def _check_form(report: Report, bundle: bytes, document: dict) -> None:
    """The bytes are the one serialisation of what they hold, and hold what the digest says
    (a bundle read whole)."""
    canonical = bundle_serialise(document)
    if canonical != bundle:
        offset = next(
            (i for i, (a, b) in enumerate(zip(canonical, bundle, strict=False)) if a != b),
            min(len(canonical), len(bundle)),
        )
        report.problems.append(f"the bundle is not in its canonical form (byte {offset})")
        index = record_line_index(bundle, offset, len(report.records))
        if index is not None:
            report.records[index].problems.append(
                f"its line in the bundle was altered (byte {offset})"
            )
    _check_fields(report, document)
    if document.get("bundle_sm3") != bundle_digest(document):
        report.problems.append("the bundle's digest (bundle_sm3) does not match its content")


def _check_fields(report: Report, document: dict) -> None:
    """The bundle's top-level fields are its format's, and the format one the check knows
    (`records` assumed: a bundle read line by line has them)."""
    fields = BUNDLE_FIELDS_OF.get(document.get("format"), BUNDLE_FIELDS)
    if set(document) | {"records"} != fields:
        report.problems.append(f"the bundle's fields are not {sorted(fields)}")
    if document.get("format") not in RECORD_FIELDS_OF:
        report.problems.append(
            f"the bundle's format is not {BUNDLE_FORMAT} "
            f"(or the older {BUNDLE_FORMAT_V2}, {BUNDLE_FORMAT_V1})"
        )


@dataclass(frozen=True)
class _Head:
    chain_id: int
    contract: str


def _check_head(
    report: Report, document: dict, chain: ChainReader, contract: str | None, chain_id: int | None
) -> _Head:
    stated_id, stated_contract = document.get("chain_id"), document.get("contract")
    try:
        whole(stated_id, "chain_id")
        address(stated_contract, "contract")
    except Invalid as exc:
        report.problems.append(str(exc))
        return _Head(-1, "")
    actual_id = chain.chain_id()
    if stated_id != actual_id:
        report.problems.append(
            f"the bundle is for chain {stated_id}; the node is chain {actual_id}"
        )
    if chain_id is not None and stated_id != chain_id:
        report.problems.append(f"the bundle is for chain {stated_id}, not the expected {chain_id}")
    if contract is not None and stated_contract.lower() != contract.lower():
        report.problems.append(
            f"the bundle names contract {stated_contract}, not the expected {contract}"
        )
    if not chain.has_code(stated_contract):
        report.problems.append(f"there is no contract at {stated_contract} on this chain")
    return _Head(stated_id, stated_contract)


@dataclass(frozen=True, slots=True)
class _Seen:
    """What the check keeps of one MCAP message: its channel, schema and times, and the SM3
    of its data (not the data: the file is read once, in bounded memory)."""

    topic: str
    schema: str
    schema_encoding: str
    schema_data: bytes  # shared by every message of the schema
    message_encoding: str
    log_time: int
    publish_time: int
    sm3: bytes  # of its data


_READ_SIZE = 1024 * 1024


def _mcap_messages(
    report: Report, document: dict, mcap: bytes | Path | IO[bytes] | None
) -> dict[int, _Seen] | None:
    """The MCAP file's messages by sequence number, after checking the file's digest: read
    twice as a stream (its SM3 and size, then its records), never held whole."""
    if mcap is None:
        return None
    if isinstance(mcap, Path):
        with mcap.open("rb") as source:
            return _mcap_messages(report, document, source)
    if isinstance(mcap, bytes | bytearray):
        return _mcap_messages(report, document, io.BytesIO(mcap))
    hasher, size = sm3_hasher(), 0
    while block := mcap.read(_READ_SIZE):
        hasher.update(block)
        size += len(block)
    stated = document.get("mcap")
    if not isinstance(stated, dict) or set(stated) != {"name", "size", "sm3"}:
        report.problems.append("the bundle does not describe its MCAP file")
    elif stated["sm3"] != "0x" + hasher.finalize().hex() or stated["size"] != size:
        report.problems.append("the MCAP file's SM3 is not the one the bundle states")
    mcap.seek(0)
    by_sequence: dict[int, _Seen] = {}
    try:
        for message in mcap_messages(mcap):
            if message.sequence in by_sequence:
                report.problems.append(
                    f"the MCAP file has two messages of sequence {message.sequence}"
                )
            by_sequence[message.sequence] = _Seen(
                topic=message.topic,
                schema=message.schema,
                schema_encoding=message.schema_encoding,
                schema_data=message.schema_data,
                message_encoding=message.message_encoding,
                log_time=message.log_time,
                publish_time=message.publish_time,
                sm3=sm3_digest(message.data),
            )
    except McapUnreadable as exc:
        report.problems.append(f"the MCAP file cannot be read: {exc}")
        return {}
    return by_sequence


# --- one record ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Counted:
    """A record that holds: whether its robot signed it, and its (signer, topic, robot,
    topic_seq) when a signed header numbers it."""

    signed: bool
    stream: tuple[str, str, str, int] | None


def _check_record(
    entry: Any,
    head: _Head,
    chain: ChainReader,
    messages: dict | None,
    fields: set[str],
    signatures: Signatures,
) -> _Counted:
    """Check one record's entry: whether its robot signed it (read from its anchored
    envelope's header, whatever the bundle's format), and its place in its stream."""
    if not isinstance(entry, dict) or set(entry) != fields:
        raise Invalid(f"its fields are not {sorted(fields)}")
    hash32(entry["digest"], "digest")
    envelope = base64_bytes(entry["envelope"], "envelope")
    if "0x" + sm3_hex(envelope) != entry["digest"]:
        raise Invalid("its envelope does not hash (SM3) to its digest")
    sealed = _sealed(envelope)
    header = sealed.header
    _check_header(entry, header)
    if "batch" in fields:
        _check_batch(entry, header)
    anchored = anchor_check(entry, chain=chain, chain_id=head.chain_id, contract=head.contract)
    if "signature" not in fields and is_signed(header):
        raise Invalid(
            f"its anchored envelope is signed by robot key {header['signer']}, but the bundle "
            f"({entry_format(fields)}) carries no signature or plaintext to check its content "
            "by: a bundle relabelled to an older format cannot pass a signed record as unsigned"
        )
    rebuilt = None
    if "signature" in fields:
        rebuilt = _check_signature(
            entry, sealed, chain, head, anchored.owner, anchored.block, signatures
        )
    _check_message(entry, messages, rebuilt)
    signed = is_signed(header)
    number = header.get("topic_seq")
    if not signed or type(number) is not int:
        return _Counted(signed, None)
    return _Counted(signed, (header["signer"], header["topic"], header["robot"], number))


def entry_format(fields: set[str]) -> str:
    return next(name for name, known in RECORD_FIELDS_OF.items() if known == fields)


def _check_batch(entry: dict, header: dict) -> None:
    """Its topic_seq and batch place are those of its envelope's header (null when the
    header has none)."""
    number = header.get("topic_seq")
    if entry["topic_seq"] != number or type(entry["topic_seq"]) is not type(number):
        raise Invalid("its topic_seq differs from its envelope's header")
    batch = {name: header[name] for name in BATCH_FIELDS} if "sig_size" in header else None
    if entry["batch"] != batch:
        raise Invalid("its batch (sig_index, sig_size, sig_path) differs from its envelope's")


def _count(tally: StreamTally, result: RecordResult, stream: tuple[str, str, str, int]) -> None:
    """Count a record that holds in its stream; a number counted twice fails the record (a
    robot never reuses one: a repeated record, or a key that signed two)."""
    signer, topic, robot, number = stream
    before = tally.add(
        signer=signer, topic=topic, robot=robot, topic_seq=number, index=result.index
    )
    if before is not None:
        result.problems.append(
            f"record #{before} carries the same topic_seq {number} of its stream "
            f"(signer {signer}, topic {topic})"
        )
        return
    result.topic_seq = number


def _sealed(envelope: bytes) -> EnvelopeInfo:
    try:
        return read_header(envelope)
    except CryptoError as exc:
        raise Invalid(f"its envelope does not parse: {exc}") from None


def _check_header(entry: dict, header: dict) -> None:
    """The record's robot, topic, type, seq and time are those its envelope's header (which
    its digest covers) states."""
    stated = {name: entry[name] for name in ("robot", "topic", "type", "seq")}
    stated["time"] = entry["captured_at"]
    sealed = {name: header.get(name) for name in ("robot", "topic", "type", "seq", "time")}
    if stated != sealed or not isinstance(entry["seq"], int) or isinstance(entry["seq"], bool):
        changed = sorted(name for name in stated if stated[name] != sealed[name])
        raise Invalid(f"its {', '.join(changed) or 'seq'} differ from its envelope's header")


def _check_signature(
    entry: dict,
    sealed: EnvelopeInfo,
    chain: ChainReader,
    head: _Head,
    owner: str,
    block: int,
    signatures: Signatures,
) -> EncodedMessage | None:
    """A signed envelope's robot signature over the plaintext the entry carries, its key on
    chain, and the message that plaintext makes (None: the envelope is unsigned)."""
    header, signature, plaintext = sealed.header, entry["signature"], entry["plaintext"]
    if not is_signed(header):
        if signature is not None or plaintext is not None:
            raise Invalid("its envelope is unsigned, yet it states a signature or a plaintext")
        return None
    if signature is None or plaintext is None:
        raise Invalid("its envelope is signed by a robot, but its signature or plaintext is null")
    if not isinstance(signature, dict) or set(signature) != SIGNATURE_FIELDS:
        raise Invalid(f"its signature's fields are not {sorted(SIGNATURE_FIELDS)}")
    content = base64_bytes(plaintext, "plaintext")
    if len(content) != sealed.ciphertext_length:
        raise Invalid("its plaintext is not as long as its envelope's ciphertext")
    signature_check(header=header, plaintext=content, signatures=signatures, **signature)
    robot_key_check(
        chain, contract=head.contract, signer=signature["signer"], owner=owner, block=block
    )
    return message_encode(data_type=header["type"], plaintext=content)


def _check_message(entry: dict, messages: dict | None, rebuilt: EncodedMessage | None) -> None:
    """Its MCAP binding is well formed, timed at its capture, is the message its signed
    plaintext makes (when signed), and (with the file) matches the message's bytes, topic,
    encodings and schema."""
    binding = entry["mcap"]
    if not isinstance(binding, dict) or set(binding) != MCAP_FIELDS:
        raise Invalid(f"its mcap fields are not {sorted(MCAP_FIELDS)}")
    sequence = whole(binding["sequence"], "mcap.sequence")
    log_time = whole(binding["log_time"], "mcap.log_time")
    captured_ns = micros(entry["captured_at"]) * 1000
    if binding["publish_time"] != log_time or log_time // 1000 != captured_ns // 1000:
        raise Invalid("its MCAP times are not its capture time")
    if binding["topic"] != entry["topic"]:
        raise Invalid("its MCAP topic is not its topic")
    data_type = entry["type"] if isinstance(entry["type"], str) else ""
    expected = {"cdr": ros2_type_name(data_type), "json": data_type}
    if expected.get(binding["message_encoding"]) != binding["schema"]:
        raise Invalid("its MCAP encoding and schema do not fit its type")
    hash32(binding["sm3"], "mcap.sm3")
    if rebuilt is not None:
        made = (
            rebuilt.message_encoding,
            rebuilt.schema_name,
            "0x" + sm3_hex(rebuilt.data),
            message_log_time(rebuilt, captured_ns),
        )
        stated = (binding["message_encoding"], binding["schema"], binding["sm3"], log_time)
        if made != stated:
            raise Invalid("its MCAP message is not the one the plaintext its robot signed makes")
    if messages is None:
        return
    message = messages.get(sequence)
    if message is None:
        raise Invalid(f"the MCAP file has no message of sequence {sequence}")
    if "0x" + message.sm3.hex() != binding["sm3"]:
        raise Invalid("its message in the MCAP file differs (SM3) from the one exported")
    found = (message.topic, message.schema, message.message_encoding, message.log_time)
    if found != (binding["topic"], binding["schema"], binding["message_encoding"], log_time):
        raise Invalid("its message's channel or time in the MCAP file differ")
    if message.publish_time != log_time:
        raise Invalid("its message's publish time in the MCAP file differs")
    schema = schema_of(schema_name=message.schema, message_encoding=message.message_encoding)
    if schema != (message.schema_encoding, message.schema_data):
        raise Invalid("its message's schema in the MCAP file is not its type's definition")


def _name_shared_sequences(sequences: dict[int, list[RecordResult]]) -> None:
    """An MCAP message belongs to one record. Of the records naming the same one, those that
    failed their own checks are the altered ones (already named); if all of them hold, none
    can be told apart and each is named."""
    for sequence, claimants in sequences.items():
        if len(claimants) > 1 and all(result.ok for result in claimants):
            for result in claimants:
                result.problems.append(f"another record has MCAP sequence {sequence}")


def _has_sequence(entry: Any) -> bool:
    binding = entry.get("mcap") if isinstance(entry, dict) else None
    return isinstance(binding, dict) and isinstance(binding.get("sequence"), int)


def _strict_json(data: bytes) -> Any:
    """ASCII JSON as a bundle holds it: no field twice in an object, no NaN or Infinity.
    UnicodeDecodeError or ValueError if it is not."""
    return _STRICT.decode(data.decode("ascii"))


def _canonical_entry(line: bytes) -> dict | None:
    """A record's line parsed once, if it is its entry's one serialisation (bundle_entry_line),
    else None. Parsed without the duplicate-field hook: a line with a field twice cannot be
    the serialisation of what it parses to (that has the field once), so the comparison
    refuses it; NaN, Infinity and fractions are refused or kept as text as _strict_json does.
    UnicodeDecodeError or ValueError if the line is not JSON."""
    entry = _LINE.decode(line.decode("ascii"))
    if isinstance(entry, dict) and bundle_entry_line(entry).encode("ascii") == line:
        return entry
    return None


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document = dict(pairs)
    if len(document) != len(pairs):
        raise ValueError("a field appears twice in one object")
    return document


def _no_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number JSON allows")


# Decoders made once (json.loads with arguments makes one a call). A bundle holds no
# fractions: one (a digit changed to "e", say) is kept as its text, which fails the form
# check at its own byte and every number check.
_STRICT = json.JSONDecoder(
    object_pairs_hook=_no_duplicates, parse_constant=_no_constant, parse_float=str
)
_LINE = json.JSONDecoder(parse_constant=_no_constant, parse_float=str)


_RECORD_ID = re.compile(rb'"record":"([0-9a-f-]{36})"')


def _name_broken_line(report: Report, bundle: bytes, exc: Exception) -> None:
    """A bundle that does not parse: name the records whose own lines do not parse (or are not
    in their canonical form), each line read alone, so that a change that breaks the JSON
    further on (a quote or a comma turned into a space) still names its own record; else the
    record on the line where the parser stopped."""
    lines = bundle.split(b"\n")
    broken = _broken_record_lines(lines)
    if broken:
        report.records = broken
        return
    position = getattr(exc, "pos", None)
    if position is None:
        position = getattr(exc, "start", None)
    if position is None:
        return
    number = bundle.count(b"\n", 0, position)
    # Records are the lines after the head and `"records":[`, before `]}` (two bytes even
    # when one of them changed) and the final empty line.
    if not 2 <= number < len(lines) or len(lines[number]) <= 2:
        return
    problem = f"its line in the bundle does not parse ({exc})"
    report.records = [RecordResult(number - 2, _record_id(lines[number]), [problem])]


def _broken_record_lines(lines: list[bytes]) -> list[RecordResult]:
    """The record lines (after the head and an intact `"records":[`, before `]}`) that do not
    parse alone, or do not read back byte for byte, trailing comma included. A line that
    follows a broken one and does not start a record (`{"` after `},`) is that record's
    line split in two by a changed byte, and joined back to it."""
    if len(lines) < 3 or lines[1] != b'"records":[':
        return []  # the skeleton itself changed: no line can be told to be whose
    records: list[tuple[bytes, str | None]] = []  # each line, and why it is broken
    for line in lines[2:]:
        if len(line) <= 2 or line.startswith(b"]}"):
            continue
        if records and records[-1][1] is not None:
            previous = records[-1][0]
            if not (line.startswith(b'{"') and previous.endswith(b"},")):
                joined = previous + b"\n" + line
                records[-1] = (joined, records[-1][1])
                continue
        records.append((line, _line_problem(line)))
    # Every record's line but the last ends with a comma; the last has none.
    for index, (line, why) in enumerate(records):
        last = index == len(records) - 1
        if why is None and line.endswith(b",") == last:
            records[index] = (line, "its comma " + ("is one too many" if last else "is missing"))
    return [
        RecordResult(index, _record_id(line), [f"its line in the bundle does not parse ({why})"])
        for index, (line, why) in enumerate(records)
        if why is not None
    ]


def _line_problem(line: bytes) -> str | None:
    """Why one record's line (with its comma, if any) is not a record's line, or None."""
    text = line.removesuffix(b",")
    try:
        entry = _strict_json(text)
    except (UnicodeDecodeError, ValueError) as exc:
        return str(exc)
    if not isinstance(entry, dict) or bundle_entry_line(entry).encode("ascii") != text:
        return "it is not in its canonical form"
    return None


def _record_id(line: bytes) -> str:
    found = _RECORD_ID.search(line)
    return found.group(1).decode() if found else "?"
