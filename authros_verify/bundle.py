"""The proof bundle's one serialisation, shared by the portal (which writes it) and the check.

The file is ASCII JSON, keys sorted, no spaces, with one record per line:

    {<every top-level field but "records">,
    "records":[
    {<record 0>},
    {<record 1>}
    ]}

so that a changed byte, even one that breaks the JSON, can be traced to the record on its
line. `bundle_sm3` is the SM3 of the compact JSON of the bundle without that field.
"""

import json
from collections.abc import Callable, Iterable, Iterator
from typing import IO, Any

from smcrypto.sm3 import sm3_hasher, sm3_hex

# v3: each record also carries its topic_seq and its place in its upload batch, and the bundle
# the portal's completeness of the selection (`streams`). v2: each record carries its robot's
# signature and the plaintext it signed (v1: not). The verifier reads all three.
BUNDLE_FORMAT = "authros-export-proofs/v3"
BUNDLE_FORMAT_V2 = "authros-export-proofs/v2"
BUNDLE_FORMAT_V1 = "authros-export-proofs/v1"
# Lines before the first record's: the top-level fields, then `"records":[`.
RECORDS_FIRST_LINE = 3


# One encoder for every line (json.dumps with arguments makes one a call).
_COMPACT = json.JSONEncoder(
    sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False
)


def _compact(value: Any) -> str:
    return _COMPACT.encode(value)


def bundle_digest(document: dict[str, Any]) -> str:
    """ "0x" + SM3 of the compact JSON of the bundle without its `bundle_sm3` field."""
    body = {name: value for name, value in document.items() if name != "bundle_sm3"}
    return "0x" + sm3_hex(_compact(body).encode("ascii"))


def bundle_serialise(document: dict[str, Any]) -> bytes:
    """The bundle's bytes, one record per line (the module's docstring)."""
    head = {name: value for name, value in document.items() if name != "records"}
    records = document.get("records", [])
    lines = [_compact(head)[:-1] + ",", '"records":[']
    lines.extend(
        _compact(entry) + ("," if i < len(records) - 1 else "") for i, entry in enumerate(records)
    )
    lines.append("]}")
    return ("\n".join(lines) + "\n").encode("ascii")


def bundle_entry_line(entry: dict[str, Any]) -> str:
    """A record entry as its line of the bundle holds it (without the line's comma)."""
    return _compact(entry)


def bundle_write(
    head: dict[str, Any], entries: Callable[[], Iterable[str]], output: IO[bytes]
) -> str:
    """Write the bundle of `head` (every top-level field but `records` and `bundle_sm3`) and
    the entries' lines (`bundle_entry_line`) to `output`, byte for byte what bundle_serialise
    makes of the whole document, holding one entry at a time: `entries()` is read twice, for
    `bundle_sm3` and to write. Answers `bundle_sm3`."""
    hasher = sm3_hasher()
    names = sorted([*head, "records"])
    hasher.update(b"{")
    for position, name in enumerate(names):
        hasher.update((("," if position else "") + _compact(name) + ":").encode("ascii"))
        if name != "records":
            hasher.update(_compact(head[name]).encode("ascii"))
            continue
        hasher.update(b"[")
        for block in _joined(entries(), ","):
            hasher.update(block)
        hasher.update(b"]")
    hasher.update(b"}")
    digest = "0x" + hasher.finalize().hex()
    output.write((_compact({**head, "bundle_sm3": digest})[:-1] + ',\n"records":[').encode())
    first = True
    for block in _joined(entries(), ",\n"):
        output.write(b"\n" + block if first else block)
        first = False
    output.write(b"\n]}\n")
    return digest


# Lines joined into blocks of about this many characters: one hash update and one write a
# block, not one a record.
_BLOCK = 1 << 20


def _joined(lines: Iterable[str], separator: str) -> Iterator[bytes]:
    """`separator.join(lines)` as ASCII, in blocks of about _BLOCK bytes (a block after the
    first starts with its separator)."""
    block: list[str] = []
    size = 0
    started = False
    for line in lines:
        if started or block:
            block.append(separator)
        block.append(line)
        size += len(line) + len(separator)
        if size >= _BLOCK:
            yield "".join(block).encode("ascii")
            block, size, started = [], 0, True
    if block:
        yield "".join(block).encode("ascii")


def record_line_index(data: bytes, offset: int, records: int) -> int | None:
    """The index of the record whose line holds byte `offset` of a bundle, if any."""
    index = data.count(b"\n", 0, max(offset, 0)) + 1 - RECORDS_FIRST_LINE
    return index if 0 <= index < records else None
