"""A file sealed with SM4-GCM in segments, written and read in constant memory.

Exports (sharing/exports/run.py) are stored sealed, never as plaintext at rest: a file of any
size is cut into segments of `segment_size` bytes, each sealed on its own (the STREAM
construction of Hoang, Reyhanitabar, Rogaway and Vizár, 2015), so that neither the writer nor
the reader ever holds more than one segment.

    header:  magic "ARS" | version 0x01 | segment size (4 bytes, big-endian) | nonce prefix (8)
    segment: SM4-GCM ciphertext of up to `segment_size` bytes || 16-byte tag

Segment i is sealed with nonce `prefix || i` (4 bytes, big-endian) and the AAD
`header || i (8 bytes) || final (1 byte: 1 for the last segment, else 0)`: a segment moved,
dropped, repeated, or a file cut short after any segment fails to open. The last segment may
be empty (an empty file is one empty final segment). Keys are used for one file only.
"""

import secrets
import struct
from collections.abc import Iterator
from typing import IO

from smcrypto import sm4
from smcrypto.errors import InvalidData

MAGIC = b"ARS"
VERSION = 1
SEGMENT_SIZE = 1 << 20
_PREFIX_SIZE = 8
HEADER_SIZE = len(MAGIC) + 1 + 4 + _PREFIX_SIZE
_MAX_SEGMENTS = 1 << 32


class SealedWriter:
    """A writable binary stream whose bytes reach `output` sealed, one segment at a time:
    it never holds more than one segment of plaintext (`buffered` says how much it holds)."""

    def __init__(self, output: IO[bytes], key: bytes, *, segment_size: int = SEGMENT_SIZE) -> None:
        if not 0 < segment_size < 1 << 31:
            raise InvalidData("a segment holds 1 byte to 2 GiB")
        self._output = output
        self._key = key
        self._segment_size = segment_size
        self._header = MAGIC + bytes([VERSION]) + struct.pack(">I", segment_size)
        self._header += secrets.token_bytes(_PREFIX_SIZE)
        self._output.write(self._header)
        self._buffer = bytearray()
        self._index = 0
        self.written = 0  # plaintext bytes taken
        self.sealed_size = len(self._header)
        self._closed = False

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def write(self, data: bytes) -> int:
        if self._closed:
            raise ValueError("the sealed file is closed")
        self._buffer += data
        self.written += len(data)
        # Keep at least one byte back: the final segment is sealed by close(), never here.
        while len(self._buffer) > self._segment_size:
            self._seal(bytes(self._buffer[: self._segment_size]), final=False)
            del self._buffer[: self._segment_size]
        return len(data)

    def close(self) -> None:
        """Seal what is left as the final segment."""
        if not self._closed:
            self._seal(bytes(self._buffer), final=True)
            self._buffer = bytearray()
            self._closed = True

    def _seal(self, plaintext: bytes, *, final: bool) -> None:
        if self._index >= _MAX_SEGMENTS:
            raise InvalidData("a sealed file holds at most 2**32 segments")
        sealed = sm4.gcm_encrypt(
            self._key,
            _nonce(self._header, self._index),
            plaintext,
            _aad(self._header, self._index, final),
        )
        self._output.write(sealed)
        self.sealed_size += len(sealed)
        self._index += 1


def sealed_open(source: IO[bytes], key: bytes) -> Iterator[bytes]:
    """The plaintext of a sealed file, segment by segment; raises smcrypto's
    AuthenticationFailed (or InvalidData) at the first segment that does not open, so a
    caller streaming it stops there."""
    header = source.read(HEADER_SIZE)
    if len(header) != HEADER_SIZE or header[:3] != MAGIC or header[3] != VERSION:
        raise InvalidData("not a sealed file of this version")
    (segment_size,) = struct.unpack(">I", header[4:8])
    sealed_size = segment_size + sm4.GCM_TAG_SIZE
    index = 0
    current = source.read(sealed_size)
    while True:
        following = source.read(sealed_size) if len(current) == sealed_size else b""
        final = not following
        yield sm4.gcm_decrypt(key, _nonce(header, index), current, _aad(header, index, final))
        if final:
            return
        current, index = following, index + 1


def _nonce(header: bytes, index: int) -> bytes:
    return header[-_PREFIX_SIZE:] + struct.pack(">I", index)


def _aad(header: bytes, index: int, final: bool) -> bytes:
    return header + struct.pack(">QB", index, 1 if final else 0)
