"""Strict values: each has one spelling, so that every changed byte of a bundle or a portal's
answer changes a value the check reads (lowercase `0x` hex, checksummed addresses, canonical
base64 and UUIDs, whole numbers). Each reader raises Invalid naming what is wrong.
"""

import base64
import binascii
import functools
import uuid
from datetime import UTC, datetime
from typing import Any

from eth_utils import to_checksum_address

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


class Invalid(ValueError):
    """One thing that does not hold; `check` names the check it belongs to, when one does
    (`signature`, `robotKeyOf`, `merkle path`, ...: what `authros_verify record` reports)."""

    def __init__(self, message: str, *, check: str = "") -> None:
        super().__init__(message)
        self.check = check


def hash32(value: Any, what: str) -> bytes:
    """The 32 bytes of "0x" and 64 lowercase hex digits (a digest, a root, a path's step).
    The digits read back as themselves or it is not one: no upper case, no space."""
    if isinstance(value, str) and len(value) == 66 and value.startswith("0x"):
        try:
            raw = bytes.fromhex(value[2:])
        except ValueError:
            raw = b""
        if len(raw) == 32 and raw.hex() == value[2:]:
            return raw
    raise Invalid(f"its {what} is not 0x and 64 lowercase hex digits")


def hashes32(values: Any, what: str) -> list[bytes]:
    """A list of hash32 texts (a proof's path), read with one hex decoding for them all: each
    "0x" and 64 lowercase hex digits, as hash32 says, or Invalid naming the first that is not."""
    if not isinstance(values, list):
        raise Invalid(f"its {what} is not a list")
    if all(type(v) is str and len(v) == 66 and v.startswith("0x") for v in values):
        digits = "".join([v[2:] for v in values])
        try:
            raw = bytes.fromhex(digits)
        except ValueError:
            raw = b""
        if len(raw) == 32 * len(values) and raw.hex() == digits:
            return [raw[i : i + 32] for i in range(0, len(raw), 32)]
    for value in values:
        hash32(value, what)  # names the step that is not one
    raise Invalid(f"its {what} is not 0x and 64 lowercase hex digits")  # pragma: no cover


def address(value: Any, what: str) -> str:
    if isinstance(value, str) and _checksummed(value):
        return value
    raise Invalid(f"its {what} is not a checksummed address")


@functools.lru_cache(maxsize=256)
def _checksummed(value: str) -> bool:
    """Whether the text is a checksummed address (keccak once per spelling: an export names
    a few owners, each on every record)."""
    try:
        return to_checksum_address(value) == value
    except ValueError:
        return False


def record_id(value: Any, what: str) -> uuid.UUID:
    try:
        parsed = uuid.UUID(value)
    except (TypeError, ValueError, AttributeError):
        parsed = None
    if parsed is None or str(parsed) != value:
        raise Invalid(f"its {what} is not a record id")
    return parsed


def whole(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise Invalid(f"its {what} is not a whole number")
    return value


def base64_bytes(value: Any, what: str) -> bytes:
    try:
        raw = base64.b64decode(value, validate=True)
    except (TypeError, ValueError, binascii.Error):
        raise Invalid(f"its {what} is not base64") from None
    if base64.b64encode(raw).decode("ascii") != value:
        raise Invalid(f"its {what} is not in canonical base64")
    return raw


def micros(value: Any, what: str = "captured_at") -> int:
    """An ISO 8601 time with a zone, as microseconds since 1970."""
    if not isinstance(value, str):
        raise Invalid(f"its {what} is not a time")
    try:
        moment = datetime.fromisoformat(value)
    except ValueError:
        raise Invalid(f"its {what} is not a time") from None
    if moment.tzinfo is None:
        raise Invalid(f"its {what} has no time zone")
    delta = moment - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
