"""Strict values: each has one spelling, so that every changed byte of a bundle or a portal's
answer changes a value the check reads (lowercase `0x` hex, checksummed addresses, canonical
base64 and UUIDs, whole numbers). Each reader raises Invalid naming what is wrong.
"""

import base64
import binascii
import functools
import re
import uuid
from datetime import UTC, datetime
from typing import Any

from eth_utils import to_checksum_address

_HASH = re.compile(r"0x[0-9a-f]{64}")
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


class Invalid(ValueError):
    """One thing that does not hold; `check` names the check it belongs to, when one does
    (`signature`, `robotKeyOf`, `merkle path`, ...: what `authros_verify record` reports)."""

    def __init__(self, message: str, *, check: str = "") -> None:
        super().__init__(message)
        self.check = check


def hash32(value: Any, what: str) -> bytes:
    if not isinstance(value, str) or not _HASH.fullmatch(value):
        raise Invalid(f"its {what} is not 0x and 64 lowercase hex digits")
    return bytes.fromhex(value[2:])


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
