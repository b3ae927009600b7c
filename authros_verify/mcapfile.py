"""An export's MCAP file read with the `mcap` library (https://mcap.dev/spec), record by record
from its first byte to its last, so that a file of any size is read in bounded memory: one
chunk at a time (uncompressed, lz4 or zstd), one message handed on at a time. CRCs are not
checked: the bundle's SM3 of the whole file is (a tamperer recomputes a CRC as easily), and a
changed byte of a message is then named by its record rather than by its chunk.

Every record of the data section is read in file order, never through the summary's indexes,
so that a message no index names is still seen (and named, if no record of the bundle is its).
A schema or channel defined twice with other content, a chunk larger than MAX_CHUNK once
decompressed, or bytes after the closing magic make the file unreadable (McapUnreadable).
"""

import io
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk

MAGIC = b"\x89MCAP0\r\n"
# The largest chunk, decompressed, the reader takes (a compressed chunk that claims more is
# refused before it is decompressed; the portal writes chunks of about 1 MiB).
MAX_CHUNK = 256 * 1024 * 1024


class McapUnreadable(ValueError):
    """The file is not an MCAP file this reader can take apart."""


@dataclass(frozen=True)
class Message:
    topic: str
    schema: str
    schema_encoding: str
    schema_data: bytes
    message_encoding: str
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


class _Counted:
    """A binary file read through, counting the bytes read (to see that nothing follows the
    closing magic)."""

    def __init__(self, source: IO[bytes]) -> None:
        self._source = source
        self.count = 0

    def read(self, size: int = -1) -> bytes:
        data = self._source.read(size)
        self.count += len(data)
        return data


def mcap_messages(source: IO[bytes] | bytes) -> Iterator[Message]:
    """Every message of the file read from `source` (a binary file at its start, or its
    bytes), in file order, with its channel's topic and encoding and its schema's name,
    encoding and definition. McapUnreadable, raised as the reading goes, if the file does not
    parse."""
    if isinstance(source, bytes | bytearray):
        source = io.BytesIO(source)
    counted = _Counted(source)
    schemas: dict[int, tuple[str, str, bytes]] = {}
    channels: dict[int, tuple[str, int, str]] = {}
    try:
        for record in StreamReader(counted, emit_chunks=True).records:
            inner = _chunk_records(record) if isinstance(record, Chunk) else (record,)
            for item in inner:
                message = _take(item, schemas, channels)
                if message is not None:
                    yield message
        if counted.read(1):
            raise McapUnreadable("bytes follow the closing magic")
    except McapUnreadable:
        raise
    except (McapError, ValueError, KeyError, struct.error, UnicodeDecodeError, EOFError) as exc:
        raise McapUnreadable(f"its records do not parse ({type(exc).__name__}: {exc})") from None


def _chunk_records(chunk: Chunk) -> list:
    if chunk.uncompressed_size > MAX_CHUNK:
        raise McapUnreadable(
            f"a chunk holds {chunk.uncompressed_size} bytes decompressed (at most {MAX_CHUNK})"
        )
    if chunk.compression not in ("", "lz4", "zstd"):
        raise McapUnreadable(f"a chunk is compressed with {chunk.compression!r}")
    return breakup_chunk(chunk)


def _take(
    record: object,
    schemas: dict[int, tuple[str, str, bytes]],
    channels: dict[int, tuple[str, int, str]],
) -> Message | None:
    """Learn a schema or a channel; a message, with what its channel and schema say."""
    if isinstance(record, Schema):
        known = (record.name, record.encoding, bytes(record.data))
        if schemas.setdefault(record.id, known) != known:
            raise McapUnreadable(f"schema {record.id} is defined twice, differently")
        return None
    if isinstance(record, Channel):
        known = (record.topic, record.schema_id, record.message_encoding)
        if channels.setdefault(record.id, known) != known:
            raise McapUnreadable(f"channel {record.id} is defined twice, differently")
        return None
    if not isinstance(record, McapMessage):
        return None
    if record.channel_id not in channels:
        raise McapUnreadable(f"a message is on channel {record.channel_id}, never defined")
    topic, schema_id, message_encoding = channels[record.channel_id]
    if schema_id not in schemas:
        raise McapUnreadable(f"channel {record.channel_id} names schema {schema_id}, never defined")
    schema, schema_encoding, schema_data = schemas[schema_id]
    return Message(
        topic=topic,
        schema=schema,
        schema_encoding=schema_encoding,
        schema_data=schema_data,
        message_encoding=message_encoding,
        sequence=record.sequence,
        log_time=record.log_time,
        publish_time=record.publish_time,
        data=bytes(record.data),
    )
