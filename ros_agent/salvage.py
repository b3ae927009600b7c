"""Reading what is left of a recording whose index or summary is missing: cut off by a power
loss or a full disk (a ROS 1 bag that was never closed, an MCAP file without its footer or summary).

rosbags reads such files through their index and refuses them. These readers go through the
file from the start, record by record, as it was written, and stop at the first record that
is not whole: every message before it is read. They offer the part of rosbags' AnyReader that
ros_agent.bags uses (connections, typestore, messages, deserialize).
"""

import bz2
import io
import struct
from collections import Counter
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

_ROSBAG_MAGIC = b"#ROSBAG V2.0\n"
_OP_MESSAGE, _OP_CHUNK, _OP_CONNECTION = 0x02, 0x05, 0x07


class SalvageError(Exception):
    """Not even the start of the file is a recording of this kind."""


@dataclass(frozen=True)
class SalvagedConnection:
    id: int
    topic: str
    msgtype: str
    msgcount: int


class _SalvageReader:
    """Common part: connections found by a first pass, messages by a second one."""

    is2 = True

    def __init__(self, path: Path, default_typestore: Typestore) -> None:
        self.path = Path(path)
        self.typestore = get_typestore(Stores.EMPTY)
        self._default = default_typestore
        self.damage = ""  # why reading stopped before the end of the file
        self.connections: list[SalvagedConnection] = []
        self._types: dict[int, tuple[str, str, str]] = {}  # id -> topic, msgtype, definition
        counts: Counter = Counter()
        for conn_id, _, _ in self._records(count_only=True):
            counts[conn_id] += 1
        self.connections = [
            SalvagedConnection(conn_id, topic, msgtype, counts[conn_id])
            for conn_id, (topic, msgtype, _) in sorted(self._types.items())
        ]
        self._register_types()

    def _register_types(self) -> None:
        known: dict[str, Any] = {}
        for _, msgtype, definition in self._types.values():
            if definition:
                try:
                    known.update(self._parse_definition(definition, msgtype))
                except Exception:  # noqa: S112 - a definition we cannot read: that type stays unknown
                    continue
        if not known:
            known = dict(self._default.fielddefs)
        self.typestore.register(known)

    def _parse_definition(self, definition: str, msgtype: str) -> dict[str, Any]:
        return get_types_from_msg(definition, msgtype)

    def messages(
        self, connections: Collection[SalvagedConnection] = ()
    ) -> Iterator[tuple[SalvagedConnection, int, bytes]]:
        wanted = {conn.id: conn for conn in connections} or {c.id: c for c in self.connections}
        for conn_id, timestamp, data in self._records(count_only=False):
            if conn_id in wanted:
                yield wanted[conn_id], timestamp, data

    def deserialize(self, rawdata: bytes, msgtype: str) -> object:
        if self.is2:
            return self.typestore.deserialize_cdr(rawdata, msgtype)
        return self.typestore.deserialize_ros1(rawdata, msgtype)

    def close(self) -> None:
        pass

    def _records(self, *, count_only: bool) -> Iterator[tuple[int, int, bytes]]:
        raise NotImplementedError


class Ros1BagSalvage(_SalvageReader):
    """A ROS 1 bag (format 2.0) read chunk by chunk, without its index."""

    is2 = False

    def _records(self, *, count_only: bool) -> Iterator[tuple[int, int, bytes]]:
        with self.path.open("rb") as stream:
            if stream.read(len(_ROSBAG_MAGIC)) != _ROSBAG_MAGIC:
                raise SalvageError("not a ROS 1 bag (format 2.0)")
            try:
                while True:
                    record = _read_bag_record(stream)
                    if record is None:
                        return
                    header, data, whole = record
                    if header.get("op") == bytes([_OP_CHUNK]):
                        yield from self._chunk(header, data)
                    elif whole:
                        yield from self._plain(header, data)
                    if not whole:
                        raise _Broken("the file ends inside a record")
            except _Broken as exc:
                self.damage = str(exc)

    def _chunk(self, header: dict[str, bytes], data: bytes) -> Iterator[tuple[int, int, bytes]]:
        compression = header.get("compression", b"none").decode()
        if compression == "bz2":
            data = _decompress_what_can_be(bz2.BZ2Decompressor(), data)
        elif compression == "lz4":
            import lz4.frame

            data = _decompress_what_can_be(lz4.frame.LZ4FrameDecompressor(), data)
        elif compression != "none":
            raise _Broken(f"chunk compression {compression!r} is unknown")
        inner = io.BytesIO(data)
        while True:
            record = _read_bag_record(inner)
            if record is None:
                return
            fields, body, whole = record
            if not whole:
                raise _Broken("the file ends inside a chunk")
            yield from self._plain(fields, body)

    def _plain(self, header: dict[str, bytes], data: bytes) -> Iterator[tuple[int, int, bytes]]:
        try:
            yield from self._plain_fields(header, data)
        except (KeyError, IndexError, struct.error, UnicodeDecodeError) as exc:
            raise _Broken(f"a record header is damaged ({type(exc).__name__})") from None

    def _plain_fields(
        self, header: dict[str, bytes], data: bytes
    ) -> Iterator[tuple[int, int, bytes]]:
        op = header.get("op", b"\x00")[0]
        if op == _OP_CONNECTION:
            fields = _bag_header_fields(data)
            conn_id = struct.unpack("<I", header["conn"])[0]
            ros1_type = fields.get("type", b"").decode()
            package, _, name = ros1_type.partition("/")
            self._types.setdefault(
                conn_id,
                (
                    header.get("topic", b"").decode(),
                    f"{package}/msg/{name}",
                    fields.get("message_definition", b"").decode(),
                ),
            )
        elif op == _OP_MESSAGE:
            conn_id = struct.unpack("<I", header["conn"])[0]
            secs, nsecs = struct.unpack("<II", header["time"])
            if conn_id in self._types:
                yield conn_id, secs * 10**9 + nsecs, data


class McapSalvage(_SalvageReader):
    """An MCAP file read record by record from the start, without its summary; a chunk cut
    off gives the messages that are whole in it."""

    def _records(self, *, count_only: bool) -> Iterator[tuple[int, int, bytes]]:
        data = self.path.read_bytes()
        if not data.startswith(_MCAP_MAGIC):
            raise SalvageError("not an MCAP file")
        self._schemas: dict[int, tuple[str, str]] = {}
        try:
            yield from self._walk(memoryview(data)[len(_MCAP_MAGIC) :], top=True)
        except _Broken as exc:
            self.damage = str(exc)

    def _walk(self, data: memoryview, *, top: bool) -> Iterator[tuple[int, int, bytes]]:
        position = 0
        while position < len(data):
            if len(data) - position < 9:
                raise _Broken("the file ends inside a record")
            opcode = data[position]
            (length,) = struct.unpack_from("<Q", data, position + 1)
            body = data[position + 9 : position + 9 + length]
            whole = len(body) == length
            position += 9 + length
            if opcode == _MCAP_CHUNK:
                yield from self._chunk(body)
            elif opcode == _MCAP_FOOTER and top:
                return
            elif whole:
                yield from self._plain(opcode, body)
            if not whole:
                raise _Broken("the file ends inside a record")

    def _chunk(self, body: memoryview) -> Iterator[tuple[int, int, bytes]]:
        reader = _Fields(body)
        reader.skip(8 + 8 + 8 + 4)
        compression = reader.string()
        size = reader.uint64()
        records = reader.rest()
        cut = len(records) < size
        records = records[:size]
        if compression == "zstd":
            import zstandard

            records = _decompress_what_can_be(
                zstandard.ZstdDecompressor().decompressobj(), bytes(records)
            )
        elif compression == "lz4":
            import lz4.frame

            records = _decompress_what_can_be(lz4.frame.LZ4FrameDecompressor(), bytes(records))
        elif compression:
            raise _Broken(f"chunk compression {compression!r} is unknown")
        yield from self._walk(memoryview(records), top=False)
        if cut:
            raise _Broken("the file ends inside a chunk")

    def _plain(self, opcode: int, body: memoryview) -> Iterator[tuple[int, int, bytes]]:
        reader = _Fields(body)
        if opcode == _MCAP_SCHEMA:
            schema_id, name, encoding = reader.uint16(), reader.string(), reader.string()
            text = bytes(reader.bytes32()).decode("utf-8", "replace")
            if encoding in ("ros2msg", "ros2idl"):
                self._schemas[schema_id] = (name, f"{encoding}\n{text}")
        elif opcode == _MCAP_CHANNEL:
            channel_id, schema_id, topic = reader.uint16(), reader.uint16(), reader.string()
            if reader.string() == "cdr" and schema_id in self._schemas:
                name, definition = self._schemas[schema_id]
                self._types.setdefault(channel_id, (topic, name, definition))
        elif opcode == _MCAP_MESSAGE:
            channel_id = reader.uint16()
            reader.skip(4)
            log_time = reader.uint64()
            reader.skip(8)
            if channel_id in self._types:
                yield channel_id, log_time, bytes(reader.rest())

    def _parse_definition(self, definition: str, msgtype: str) -> dict[str, Any]:
        encoding, _, text = definition.partition("\n")
        if encoding == "ros2idl":
            return get_types_from_idl(text)
        return get_types_from_msg(text, msgtype)


_MCAP_MAGIC = b"\x89MCAP0\r\n"
_MCAP_FOOTER, _MCAP_SCHEMA, _MCAP_CHANNEL, _MCAP_MESSAGE, _MCAP_CHUNK = 0x02, 0x03, 0x04, 0x05, 0x06


class _Broken(Exception):
    """A record that is not whole: reading stops here."""


class _Fields:
    """Little-endian fields of an MCAP record body; _Broken where the body is too short."""

    def __init__(self, body: memoryview) -> None:
        self._body = body
        self._at = 0

    def _take(self, size: int) -> memoryview:
        if self._at + size > len(self._body):
            raise _Broken("a record is cut short")
        part = self._body[self._at : self._at + size]
        self._at += size
        return part

    def skip(self, size: int) -> None:
        self._take(size)

    def uint16(self) -> int:
        return struct.unpack("<H", self._take(2))[0]

    def uint64(self) -> int:
        return struct.unpack("<Q", self._take(8))[0]

    def string(self) -> str:
        (size,) = struct.unpack("<I", self._take(4))
        return bytes(self._take(size)).decode("utf-8", "replace")

    def bytes32(self) -> memoryview:
        (size,) = struct.unpack("<I", self._take(4))
        return self._take(size)

    def rest(self) -> memoryview:
        part = self._body[self._at :]
        self._at = len(self._body)
        return part


def _decompress_what_can_be(decompressor: Any, data: bytes) -> bytes:
    """As much of `data` as decompresses (all of it, or the part before it was cut off)."""
    try:
        return decompressor.decompress(data)
    except Exception as exc:  # each codec has its own error for a damaged stream
        raise _Broken(f"a chunk does not decompress: {exc}") from None


def _read_bag_record(stream: Any) -> tuple[dict[str, bytes], bytes, bool] | None:
    """One record of a ROS 1 bag: (header fields, data, whether the data is whole); None at
    a clean end of the stream."""
    raw = stream.read(4)
    if not raw:
        return None
    if len(raw) < 4:
        raise _Broken("the file ends inside a record")
    (header_len,) = struct.unpack("<I", raw)
    header = stream.read(header_len)
    if len(header) < header_len:
        raise _Broken("the file ends inside a record header, or a record header is damaged")
    fields = _bag_header_fields(header)
    if "op" not in fields:
        raise _Broken("a record without an op code: the file is damaged here")
    raw = stream.read(4)
    if len(raw) < 4:
        raise _Broken("the file ends inside a record")
    (data_len,) = struct.unpack("<I", raw)
    data = stream.read(data_len)
    return fields, data, len(data) == data_len


def _bag_header_fields(header: bytes) -> dict[str, bytes]:
    fields: dict[str, bytes] = {}
    position = 0
    while position + 4 <= len(header):
        (length,) = struct.unpack_from("<I", header, position)
        position += 4
        field = header[position : position + length]
        if len(field) < length or b"=" not in field:
            raise _Broken("a record header is damaged")
        name, _, value = field.partition(b"=")
        fields[name.decode("ascii", "replace")] = value
        position += length
    return fields


def salvage_reader(
    path: Path, default_typestore: Typestore, *, ros1: bool = False
) -> _SalvageReader | None:
    """A salvage reader for a .bag (or, with ros1, any ROS 1 bag) or .mcap file, or None."""
    if ros1 or path.suffix == ".bag":
        return Ros1BagSalvage(path, default_typestore)
    if path.suffix == ".mcap":
        return McapSalvage(path, default_typestore)
    return None
