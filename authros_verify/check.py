"""The check of a proof bundle: every record's envelope, proof and anchor against the chain,
and every record's MCAP message against the file; the bundle's own form and digest.

A record fails if anything about it does not hold; the bundle fails if any record does, or
if something outside the records (its form, digest, chain, contract, MCAP file) does not.
"""

import base64
import binascii
import json
import re
import uuid
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

from eth_utils import to_checksum_address

from authros_verify.bundle import (
    BUNDLE_FORMAT,
    bundle_digest,
    bundle_serialise,
    record_line_index,
)
from authros_verify.chain import ChainReader
from authros_verify.mcapfile import McapUnreadable, mcap_messages
from smcrypto.envelope import read_header
from smcrypto.errors import CryptoError
from smcrypto.merkle import leaf_hash, proof_holds
from smcrypto.sm3 import sm3_hex

_HASH = re.compile(r"0x[0-9a-f]{64}")
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
RECORD_FIELDS = {
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
ANCHOR_FIELDS = {"chain_id", "contract", "sender", "tx", "block"}
MCAP_FIELDS = {
    "topic",
    "sequence",
    "log_time",
    "publish_time",
    "message_encoding",
    "schema",
    "sm3",
}
BUNDLE_FIELDS = {
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


class Invalid(ValueError):
    """One thing about the bundle or a record that does not hold."""


@dataclass
class RecordResult:
    index: int
    record: str  # the record id as the bundle states it
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class Report:
    problems: list[str] = field(default_factory=list)  # about the bundle as a whole
    records: list[RecordResult] = field(default_factory=list)

    @property
    def failed(self) -> list[RecordResult]:
        return [result for result in self.records if not result.ok]

    @property
    def ok(self) -> bool:
        return not self.problems and bool(self.records) and not self.failed


def verify(
    bundle: bytes,
    *,
    chain: ChainReader,
    mcap: bytes | None = None,
    contract: str | None = None,
    chain_id: int | None = None,
) -> Report:
    """Check the bundle's bytes (and the MCAP file's, if given) against the chain.

    `contract` and `chain_id` are what the verifier knows independently (the portal's
    published contract); without them the bundle's own are checked for consistency only.
    Raises ChainUnreachable if the node cannot be asked.
    """
    report = Report()
    try:
        document = json.loads(
            bundle.decode("ascii"),
            object_pairs_hook=_no_duplicates,
            parse_constant=_no_constant,
            # A bundle holds no fractions: one (a digit changed to "e", say) is kept as its
            # text, which fails the form check at its own byte and every number check.
            parse_float=str,
        )
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
    sequences: set[int] = set()
    for result, entry in zip(report.records, entries, strict=True):
        try:
            _check_record(entry, head, chain, messages, sequences)
        except Invalid as exc:
            result.problems.append(str(exc))
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            result.problems.append(f"its entry is malformed ({type(exc).__name__}: {exc})")
    if messages is not None:
        named = {entry["mcap"]["sequence"] for entry in entries if _has_sequence(entry)}
        extra = sorted(set(messages) - named)
        if extra:
            report.problems.append(f"the MCAP file has messages no record names: {extra[:5]}")
    return report


# --- the bundle as a whole -------------------------------------------------------------------


def _check_form(report: Report, bundle: bytes, document: dict) -> None:
    """The bytes are the one serialisation of what they hold, and hold what the digest says."""
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
    if set(document) != BUNDLE_FIELDS:
        report.problems.append(f"the bundle's fields are not {sorted(BUNDLE_FIELDS)}")
    if document.get("format") != BUNDLE_FORMAT:
        report.problems.append(f"the bundle's format is not {BUNDLE_FORMAT}")
    if document.get("bundle_sm3") != bundle_digest(document):
        report.problems.append("the bundle's digest (bundle_sm3) does not match its content")


@dataclass(frozen=True)
class _Head:
    chain_id: int
    contract: str


def _check_head(
    report: Report, document: dict, chain: ChainReader, contract: str | None, chain_id: int | None
) -> _Head:
    stated_id, stated_contract = document.get("chain_id"), document.get("contract")
    try:
        _integer(stated_id, "chain_id")
        _address(stated_contract, "contract")
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


def _mcap_messages(report: Report, document: dict, mcap: bytes | None) -> dict | None:
    """The MCAP file's messages by sequence number, after checking the file's digest."""
    if mcap is None:
        return None
    stated = document.get("mcap")
    if not isinstance(stated, dict) or set(stated) != {"name", "size", "sm3"}:
        report.problems.append("the bundle does not describe its MCAP file")
    elif stated["sm3"] != "0x" + sm3_hex(mcap) or stated["size"] != len(mcap):
        report.problems.append("the MCAP file's SM3 is not the one the bundle states")
    try:
        messages = mcap_messages(mcap)
    except McapUnreadable as exc:
        report.problems.append(f"the MCAP file cannot be read: {exc}")
        return {}
    by_sequence: dict[int, Any] = {}
    for message in messages:
        if message.sequence in by_sequence:
            report.problems.append(f"the MCAP file has two messages of sequence {message.sequence}")
        by_sequence[message.sequence] = message
    return by_sequence


# --- one record ------------------------------------------------------------------------------


def _check_record(
    entry: Any, head: _Head, chain: ChainReader, messages: dict | None, sequences: set[int]
) -> None:
    if not isinstance(entry, dict) or set(entry) != RECORD_FIELDS:
        raise Invalid(f"its fields are not {sorted(RECORD_FIELDS)}")
    record_id = _uuid(entry["record"], "record")
    owner = _address(entry["owner"], "owner")
    digest = _hash(entry["digest"], "digest")
    envelope = _base64(entry["envelope"], "envelope")
    if "0x" + sm3_hex(envelope) != entry["digest"]:
        raise Invalid("its envelope does not hash (SM3) to its digest")
    _check_header(entry, envelope)
    anchor = entry["anchor"]
    if not isinstance(anchor, dict) or set(anchor) != ANCHOR_FIELDS:
        raise Invalid(f"its anchor's fields are not {sorted(ANCHOR_FIELDS)}")
    if anchor["chain_id"] != head.chain_id or anchor["contract"] != head.contract:
        raise Invalid("its anchor names another chain or contract than the bundle")
    sender = _address(anchor["sender"], "anchor.sender")
    tx = _hash(anchor["tx"], "anchor.tx")
    block = _integer(anchor["block"], "anchor.block")
    if sender != owner:
        raise Invalid("it was anchored by another account than its owner's")
    if entry["mode"] == "root":
        _check_root(entry, head, chain, owner, record_id, digest, tx, block)
    elif entry["mode"] == "record":
        _check_slot(entry, head, chain, owner, record_id, digest, tx, block)
    else:
        raise Invalid("its mode is neither root nor record")
    _check_message(entry, messages, sequences)


def _check_header(entry: dict, envelope: bytes) -> None:
    """The record's robot, topic, type, seq and time are those its envelope's header (which
    its digest covers) states."""
    try:
        header = read_header(envelope).header
    except CryptoError as exc:
        raise Invalid(f"its envelope does not parse: {exc}") from None
    stated = {name: entry[name] for name in ("robot", "topic", "type", "seq")}
    stated["time"] = entry["captured_at"]
    sealed = {name: header.get(name) for name in ("robot", "topic", "type", "seq", "time")}
    if stated != sealed or not isinstance(entry["seq"], int) or isinstance(entry["seq"], bool):
        changed = sorted(name for name in stated if stated[name] != sealed[name])
        raise Invalid(f"its {', '.join(changed) or 'seq'} differ from its envelope's header")


def _check_root(
    entry: dict,
    head: _Head,
    chain: ChainReader,
    owner: str,
    record_id: uuid.UUID,
    digest: bytes,
    tx: bytes,
    block: int,
) -> None:
    index = _integer(entry["leaf_index"], "leaf_index")
    size = _integer(entry["tree_size"], "tree_size")
    root = _hash(entry["root"], "root")
    if not isinstance(entry["path"], list):
        raise Invalid("its path is not a list")
    path = [_hash(step, "path") for step in entry["path"]]
    if not proof_holds(leaf_hash(owner, record_id, digest), index, size, path, root):
        raise Invalid("its inclusion proof does not fold to its root")
    anchored = chain.root_of(head.contract, owner, root)
    if anchored.size == 0:
        raise Invalid("its root is not anchored on chain by its owner")
    if anchored.size != size or anchored.block != block:
        raise Invalid(
            f"the chain holds its root with size {anchored.size} in block {anchored.block}, "
            f"not size {size} in block {block}"
        )
    receipt = chain.receipt(entry["anchor"]["tx"])
    if receipt is None or receipt.status != 1 or receipt.block != block:
        raise Invalid("its transaction is not a successful one in its block")
    if receipt.root_anchored(head.contract, owner, root) != size:
        raise Invalid("its transaction's receipt holds no RootAnchored event for its root")


def _check_slot(
    entry: dict,
    head: _Head,
    chain: ChainReader,
    owner: str,
    record_id: uuid.UUID,
    digest: bytes,
    tx: bytes,
    block: int,
) -> None:
    """Record mode: dataQuery(id) holds the digest, and the transaction uploaded it."""
    if (entry["path"], entry["leaf_index"], entry["tree_size"]) != ([], 0, 1) or entry[
        "root"
    ] != entry["digest"]:
        raise Invalid("its record-mode proof is not (no path, leaf 0 of 1, root = digest)")
    slot_id = record_id.bytes + bytes(16)
    anchored = chain.data_query(head.contract, slot_id)
    if anchored.owner.lower() != owner.lower() or anchored.digest != digest:
        raise Invalid("the chain holds another owner or digest for its id (dataQuery)")
    receipt = chain.receipt(entry["anchor"]["tx"])
    if receipt is None or receipt.status != 1 or receipt.block != block:
        raise Invalid("its transaction is not a successful one in its block")
    if receipt.data_uploaded(head.contract, slot_id, owner) != digest:
        raise Invalid("its transaction's receipt holds no DataUploaded event for it")


def _check_message(entry: dict, messages: dict | None, sequences: set[int]) -> None:
    """Its MCAP binding is well formed, timed at its capture, and (with the file) matches the
    message's bytes, topic and encodings."""
    binding = entry["mcap"]
    if not isinstance(binding, dict) or set(binding) != MCAP_FIELDS:
        raise Invalid(f"its mcap fields are not {sorted(MCAP_FIELDS)}")
    sequence = _integer(binding["sequence"], "mcap.sequence")
    if sequence in sequences:
        raise Invalid(f"another record has MCAP sequence {sequence}")
    sequences.add(sequence)
    log_time = _integer(binding["log_time"], "mcap.log_time")
    if binding["publish_time"] != log_time or log_time // 1000 != _micros(entry["captured_at"]):
        raise Invalid("its MCAP times are not its capture time")
    if binding["topic"] != entry["topic"]:
        raise Invalid("its MCAP topic is not its topic")
    expected = {"cdr": _ros2_name(entry["type"]), "json": entry["type"]}
    if expected.get(binding["message_encoding"]) != binding["schema"]:
        raise Invalid("its MCAP encoding and schema do not fit its type")
    _hash(binding["sm3"], "mcap.sm3")
    if messages is None:
        return
    message = messages.get(sequence)
    if message is None:
        raise Invalid(f"the MCAP file has no message of sequence {sequence}")
    if "0x" + sm3_hex(message.data) != binding["sm3"]:
        raise Invalid("its message in the MCAP file differs (SM3) from the one exported")
    found = (message.topic, message.schema, message.message_encoding, message.log_time)
    if found != (binding["topic"], binding["schema"], binding["message_encoding"], log_time):
        raise Invalid("its message's channel or time in the MCAP file differ")
    if message.publish_time != log_time:
        raise Invalid("its message's publish time in the MCAP file differs")


# --- strict values: one spelling each, so that every changed byte changes a value -----------


def _hash(value: Any, what: str) -> bytes:
    if not isinstance(value, str) or not _HASH.fullmatch(value):
        raise Invalid(f"its {what} is not 0x and 64 lowercase hex digits")
    return bytes.fromhex(value[2:])


def _address(value: Any, what: str) -> str:
    try:
        if isinstance(value, str) and to_checksum_address(value) == value:
            return value
    except ValueError:
        pass
    raise Invalid(f"its {what} is not a checksummed address")


def _uuid(value: Any, what: str) -> uuid.UUID:
    try:
        parsed = uuid.UUID(value)
    except (TypeError, ValueError, AttributeError):
        parsed = None
    if parsed is None or str(parsed) != value:
        raise Invalid(f"its {what} is not a record id")
    return parsed


def _integer(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise Invalid(f"its {what} is not a whole number")
    return value


def _base64(value: Any, what: str) -> bytes:
    try:
        raw = base64.b64decode(value, validate=True)
    except (TypeError, ValueError, binascii.Error):
        raise Invalid(f"its {what} is not base64") from None
    if base64.b64encode(raw).decode("ascii") != value:
        raise Invalid(f"its {what} is not in canonical base64")
    return raw


def _micros(value: Any) -> int:
    if not isinstance(value, str):
        raise Invalid("its captured_at is not a time")
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise Invalid("its captured_at is not a time") from None
    if moment.tzinfo is None:
        raise Invalid("its captured_at has no time zone")
    delta = moment - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds


def _ros2_name(data_type: Any) -> str:
    if not isinstance(data_type, str):
        return ""
    if data_type.count("/") >= 2:
        return data_type
    package, _, name = data_type.partition("/")
    return f"{package}/msg/{name}"


def _has_sequence(entry: Any) -> bool:
    binding = entry.get("mcap") if isinstance(entry, dict) else None
    return isinstance(binding, dict) and isinstance(binding.get("sequence"), int)


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    document = dict(pairs)
    if len(document) != len(pairs):
        raise ValueError("a field appears twice in one object")
    return document


def _no_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number JSON allows")


_RECORD_ID = re.compile(rb'"record":"([0-9a-f-]{36})"')


def _name_broken_line(report: Report, bundle: bytes, exc: Exception) -> None:
    """A bundle that does not parse: name the record on the line where it breaks."""
    position = getattr(exc, "pos", None)
    if position is None:
        position = getattr(exc, "start", None)
    if position is None:
        return
    lines = bundle.split(b"\n")
    number = bundle.count(b"\n", 0, position)
    # Records are the lines after the head and `"records":[`, before `]}` (two bytes even
    # when one of them changed) and the final empty line.
    if not 2 <= number < len(lines) or len(lines[number]) <= 2:
        return
    index = number - 2
    line = lines[number]
    found = _RECORD_ID.search(line)
    record = found.group(1).decode() if found else "?"
    report.records = [
        RecordResult(index, record, [f"its line in the bundle does not parse ({exc})"])
    ]
