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
import re
from collections.abc import Iterable, Iterator
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
) -> Report:
    """Check the bundle (its bytes, or its path) and the MCAP file, if given (its bytes, its
    path, or a binary file at its start), against the chain.

    A bundle in its canonical form (every line its own, as the portal writes it) is read line
    by line, twice (its form and digest, then each record), never held whole; one that is not
    is read whole, so that the record whose line changed is named. The MCAP file is read as a
    stream (`_mcap_messages`). `contract` and `chain_id` are what the verifier knows
    independently (the portal's published contract); without them the bundle's own are
    checked for consistency only. Raises ChainUnreachable if the node cannot be asked; OSError
    if a file cannot be read.
    """
    with _lines_of(bundle) as lines:
        form = _form_read(lines)
    if form is None:
        data = bundle if isinstance(bundle, bytes) else bundle.read_bytes()
        return _verify_whole(data, chain=chain, mcap=mcap, contract=contract, chain_id=chain_id)
    report = Report()
    document = form.head
    if not form.digest_holds:
        report.problems.append("the bundle's digest (bundle_sm3) does not match its content")
    _check_fields(report, document)
    head = _check_head(report, document, chain, contract, chain_id)
    messages = _mcap_messages(report, document, mcap)

    def entries() -> Iterator[tuple[RecordResult, Any]]:
        with _lines_of(bundle) as lines:
            for index, line in enumerate(_record_lines(lines)):
                entry = _strict_json(line.removesuffix(b","))
                result = RecordResult(index, str(entry.get("record")))
                report.records.append(result)
                yield result, entry

    _check_records(report, entries(), document, head, chain, messages)
    return report


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
    head = _check_head(report, document, chain, contract, chain_id)
    messages = _mcap_messages(report, document, mcap)
    pairs = zip(report.records, entries, strict=True)
    _check_records(report, pairs, document, head, chain, messages)
    return report


def _check_records(
    report: Report,
    entries: Iterable[tuple[RecordResult, Any]],
    document: dict,
    head: "_Head",
    chain: ChainReader,
    messages: dict | None,
) -> None:
    """Check each record (keeping its result, never its entry), count the records that hold
    in their streams, and name the MCAP messages no record names."""
    fields = RECORD_FIELDS_OF.get(document.get("format"), RECORD_FIELDS)
    # Kept per record, so kept small: the first record naming each MCAP sequence (all of them
    # only for a sequence named twice), and each counted record's stream (one tuple per
    # stream, shared) and number.
    sequences: dict[int, RecordResult] = {}
    shared: dict[int, list[RecordResult]] = {}
    streams: dict[tuple[str, str, str], tuple[str, str, str]] = {}
    signatures = Signatures()
    numbered: list[tuple[RecordResult, tuple[str, str, str], int]] = []
    for result, entry in entries:
        try:
            counted = _check_record(entry, head, chain, messages, fields, signatures)
            result.signed = counted.signed
            if counted.stream is not None:
                *key, number = counted.stream
                numbered.append((result, streams.setdefault(tuple(key), tuple(key)), number))
        except Invalid as exc:
            result.problems.append(str(exc))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            result.problems.append(f"its entry is malformed ({type(exc).__name__}: {exc})")
        if _has_sequence(entry):
            sequence = entry["mcap"]["sequence"]
            first = sequences.setdefault(sequence, result)
            if first is not result:
                shared.setdefault(sequence, [first]).append(result)
    report.signatures_verified = signatures.verified
    _name_shared_sequences(shared)
    tally = StreamTally()
    for result, stream, number in numbered:
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
        extra = sorted(set(messages) - set(sequences))
        if extra:
            report.problems.append(f"the MCAP file has messages no record names: {extra[:5]}")


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


def _record_lines(lines: Iterator[bytes]) -> Iterator[bytes]:
    """The record lines of a bundle whose form holds (_form_read): after the head and
    `"records":[`, before `]}`."""
    for number, line in enumerate(lines):
        if number < 2:
            continue
        if line == b"]}\n":
            return
        yield line.removesuffix(b"\n")


@dataclass(frozen=True)
class _Form:
    head: dict  # every top-level field but `records`
    digest_holds: bool


def _form_read(lines: Iterator[bytes]) -> _Form | None:
    """The head of a bundle whose every line is in its canonical form (bundle_serialise's,
    record by record), and whether `bundle_sm3` is the digest of its content, computed as the
    lines go by; None if any line is not (then the bundle is read whole to name it)."""
    lines = (_unbroken(line) for line in lines)
    try:
        first = next(lines)
        head = _strict_json(first[:-1] + b"}") if first.endswith(b",") else None
        if not isinstance(head, dict) or "records" in head:
            return None
        if (bundle_entry_line(head)[:-1] + ",").encode("ascii") != first:
            return None
        if next(lines) != b'"records":[':
            return None
        body = {name: value for name, value in head.items() if name != "bundle_sm3"}
        names = sorted([*body, "records"])
        hasher = sm3_hasher()
        hasher.update(b"{")
        after = names[names.index("records") + 1 :]
        for position, name in enumerate(names[: names.index("records")]):
            hasher.update((("," if position else "") + _field(name, body[name])).encode("ascii"))
        hasher.update(("," if names[0] != "records" else "").encode("ascii") + b'"records":[')
        count, pending = 0, None  # a record's line is known to be the last at the next line
        for line in lines:
            if line == b"]}":
                break
            if pending is not None:
                if not pending.endswith(b","):
                    return None
                _entry_hashed(hasher, pending[:-1], first_entry=count == 0)
                count += 1
            pending = line
        else:
            return None  # no closing line
        if pending is not None:
            if pending.endswith(b","):
                return None
            _entry_hashed(hasher, pending, first_entry=count == 0)
        if next(lines, None) is not None:
            return None
        hasher.update(b"]")
        for name in after:
            hasher.update(("," + _field(name, body[name])).encode("ascii"))
        hasher.update(b"}")
    except (StopIteration, UnicodeDecodeError, ValueError, _NotCanonical):
        return None
    return _Form(head, head.get("bundle_sm3") == "0x" + hasher.finalize().hex())


class _NotCanonical(Exception):
    """A line is not the one the bundle's serialisation makes."""


def _unbroken(line: bytes) -> bytes:
    """A line without its line break; every line of a bundle has one."""
    if not line.endswith(b"\n"):
        raise _NotCanonical
    return line[:-1]


def _field(name: str, value: Any) -> str:
    return bundle_entry_line({name: value})[1:-1]


def _entry_hashed(hasher: Any, line: bytes, *, first_entry: bool) -> None:
    """A record's line (without its comma), checked to be its record's one serialisation,
    added to the digest."""
    entry = _strict_json(line)
    if not isinstance(entry, dict) or bundle_entry_line(entry).encode("ascii") != line:
        raise _NotCanonical
    hasher.update(line if first_entry else b"," + line)


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
    return json.loads(
        data.decode("ascii"),
        object_pairs_hook=_no_duplicates,
        parse_constant=_no_constant,
        # A bundle holds no fractions: one (a digit changed to "e", say) is kept as its text,
        # which fails the form check at its own byte and every number check.
        parse_float=str,
    )


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document = dict(pairs)
    if len(document) != len(pairs):
        raise ValueError("a field appears twice in one object")
    return document


def _no_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number JSON allows")


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
