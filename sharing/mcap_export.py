"""Verified records written as an MCAP file that Foxglove or Lichtblick opens: a schema per
type and a channel per topic (and encoding), profile `ros2`, chunks uncompressed.

What message each record becomes (`ros2msg` schemas, `cdr` messages serialised by rosbags, or
its Fig. 4 record as `json`) is decided by authros_verify/messages.py from the record's type and
plaintext alone, because the verifier rebuilds a signed record's message by the same rules and
compares it byte for byte with the file's (docs/export.md). This module only writes the file.
"""

from typing import IO

from mcap.writer import CompressionType, Writer

from authros_verify.messages import EncodedMessage


class McapBuilder:
    """An MCAP file written message by message: a schema per type and a channel per topic
    (and encoding), registered when first needed. Chunks are not compressed, so that any tool
    finds each message's bytes in the file (authros_verify reads compressed chunks too)."""

    def __init__(self, output: IO[bytes], *, profile: str = "ros2") -> None:
        self._writer = Writer(output, compression=CompressionType.NONE)
        self._writer.start(profile=profile, library="authros-portal")
        self._schemas: dict[tuple[str, str], int] = {}
        self._channels: dict[tuple[str, str, int], int] = {}

    def add(self, *, topic: str, message: EncodedMessage, log_time: int, sequence: int) -> None:
        schema_key = (message.schema_name, message.schema_encoding)
        if schema_key not in self._schemas:
            self._schemas[schema_key] = self._writer.register_schema(
                name=message.schema_name, encoding=message.schema_encoding, data=message.schema
            )
        schema_id = self._schemas[schema_key]
        channel_key = (topic, message.message_encoding, schema_id)
        if channel_key not in self._channels:
            self._channels[channel_key] = self._writer.register_channel(
                topic=topic, message_encoding=message.message_encoding, schema_id=schema_id
            )
        self._writer.add_message(
            channel_id=self._channels[channel_key],
            log_time=log_time,
            publish_time=log_time,
            data=message.data,
            sequence=sequence,
        )

    def finish(self) -> None:
        self._writer.finish()
