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
    message_encoding: str
    sequence: int
    log_time: int
    publish_time: int
    data: bytes


def mcap_messages(data: bytes) -> list[Message]:
    """Every message of the file, in file order, with its channel's topic and encodings."""
    if not (data.startswith(MAGIC) and data.endswith(MAGIC)):
        raise McapUnreadable("it does not start and end with the MCAP magic")
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, int, str]] = {}
    raw: list[tuple[int, int, int, int, bytes]] = []
    try:
        _walk(data[len(MAGIC) : -len(MAGIC)], schemas, channels, raw)
        return [
            Message(
                topic=channels[channel][0],
                schema=schemas[channels[channel][1]],
                message_encoding=channels[channel][2],
                sequence=sequence,
                log_time=log_time,
                publish_time=publish_time,
                data=body,
            )
            for channel, sequence, log_time, publish_time, body in raw
        ]
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
            schema_id, name, _ = _u16_string(content, 0)
            schemas.setdefault(schema_id, name)
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


def _u16_string(content: bytes, offset: int) -> tuple[int, str, int]:
    (schema_id,) = struct.unpack_from("<H", content, offset)
    name, at = _string(content, offset + 2)
    return schema_id, name, at
