"""Just enough of MCAP (https://mcap.dev/spec) to find each message's bytes in an export:
records are opcode (1 byte), length (8, little-endian), content; messages sit in chunks,
which the portal writes uncompressed."""

import struct
from dataclasses import dataclass

MAGIC = b"\x89MCAP0\r\n"
_CHANNEL, _MESSAGE, _CHUNK, _SCHEMA = 0x04, 0x05, 0x06, 0x03


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


def mcap_messages(data: bytes) -> list[Message]:
    """Every message of the file, in file order, with its channel's topic and encoding and
    its schema's name, encoding and definition."""
    if not (data.startswith(MAGIC) and data.endswith(MAGIC)):
        raise McapUnreadable("it does not start and end with the MCAP magic")
    schemas: dict[int, tuple[str, str, bytes]] = {}
    channels: dict[int, tuple[str, int, str]] = {}
    raw: list[tuple[int, int, int, int, bytes]] = []
    try:
        _walk(data[len(MAGIC) : -len(MAGIC)], schemas, channels, raw)
        messages = []
        for channel, sequence, log_time, publish_time, body in raw:
            topic, schema_id, message_encoding = channels[channel]
            schema, schema_encoding, schema_data = schemas[schema_id]
            messages.append(
                Message(
                    topic=topic,
                    schema=schema,
                    schema_encoding=schema_encoding,
                    schema_data=schema_data,
                    message_encoding=message_encoding,
                    sequence=sequence,
                    log_time=log_time,
                    publish_time=publish_time,
                    data=body,
                )
            )
        return messages
    except (struct.error, KeyError, UnicodeDecodeError, IndexError) as exc:
        raise McapUnreadable(f"its records do not parse ({type(exc).__name__})") from None


def _walk(data: bytes, schemas: dict, channels: dict, raw: list) -> None:
    offset = 0
    while offset < len(data):
        opcode, length = struct.unpack_from("<BQ", data, offset)
        offset += 9
        content = data[offset : offset + length]
        if len(content) != length:
            raise McapUnreadable("a record runs past the end of the file")
        offset += length
        if opcode == _SCHEMA:
            schema = _schema(content)
            if schemas.setdefault(schema[0], schema[1:]) != schema[1:]:
                raise McapUnreadable(f"schema {schema[0]} is defined twice, differently")
        elif opcode == _CHANNEL:
            channel_id, schema_id = struct.unpack_from("<HH", content, 0)
            topic, at = _string(content, 4)
            encoding, _ = _string(content, at)
            known = channels.setdefault(channel_id, (topic, schema_id, encoding))
            if known != (topic, schema_id, encoding):
                raise McapUnreadable(f"channel {channel_id} is defined twice, differently")
        elif opcode == _MESSAGE:
            channel, sequence, log_time, publish_time = struct.unpack_from("<HIQQ", content, 0)
            raw.append((channel, sequence, log_time, publish_time, content[22:]))
        elif opcode == _CHUNK:
            compression, at = _string(content, 28)
            if compression:
                raise McapUnreadable(f"a chunk is compressed ({compression})")
            (size,) = struct.unpack_from("<Q", content, at)
            records = content[at + 8 : at + 8 + size]
            if len(records) != size:
                raise McapUnreadable("a chunk runs past its record")
            _walk(records, schemas, channels, raw)


def _string(content: bytes, offset: int) -> tuple[str, int]:
    (length,) = struct.unpack_from("<I", content, offset)
    text = content[offset + 4 : offset + 4 + length]
    if len(text) != length:
        raise McapUnreadable("a string runs past its record")
    return text.decode("utf-8"), offset + 4 + length


def _schema(content: bytes) -> tuple[int, str, str, bytes]:
    """A Schema record: id, name, encoding and data (the definition readers decode by)."""
    (schema_id,) = struct.unpack_from("<H", content, 0)
    name, at = _string(content, 2)
    encoding, at = _string(content, at)
    (length,) = struct.unpack_from("<I", content, at)
    data = content[at + 4 : at + 4 + length]
    if len(data) != length:
        raise McapUnreadable("a schema runs past its record")
    return schema_id, name, encoding, data
