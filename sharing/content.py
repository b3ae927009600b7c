"""How a decrypted ROS record is shown: the paper's Fig. 4 JSON, an image, odometry rows (plots
are sharing/series.py's, drawn by static/portal/series-plot.js).

Pure functions of the plaintext the integrity check let through: no request, no database.
A verified record is still whatever its robot (or a thief of its key) sealed, so nothing here
trusts its shape: numbers are parsed within bounds (at most MAX_INT_DIGITS digits, finite
floats), nesting is limited, every formatting function takes any JSON value, and a record
that cannot be interpreted is shown as raw text with a note instead of failing the page.
"""

import base64
import binascii
import json
import logging
import math
from dataclasses import dataclass, field
from typing import Any, TypeGuard

logger = logging.getLogger(__name__)

ODOMETRY = "nav_msgs/Odometry"
IMAGE_TYPES = {"sensor_msgs/Image", "sensor_msgs/CompressedImage"}
MISSING = "-"
NOT_INTERPRETED = "this record's content could not be interpreted"
_IMAGE_MAGIC = {b"\x89PNG\r\n\x1a\n": "image/png", b"\xff\xd8\xff": "image/jpeg"}

# Digits of an integer in a record: more is no measurement, and float() of it overflows.
MAX_INT_DIGITS = 30
# Nesting of a record's JSON: the agent's records are a few levels deep.
MAX_DEPTH = 64
# Bytes of an uninterpretable record shown on its page; the download has all of it.
RAW_SHOWN_BYTES = 64 * 1024
# Characters of one text value in the odometry table.
TEXT_SHOWN_CHARS = 200
# Pixels an image's declared width or height may have to be used as the <img> size.
IMAGE_SIDE_MAX = 100_000


class Uninterpretable(ValueError):
    """A record's plaintext that is not JSON the pages can show; the message says why."""


# The labels of the record format's fields (DESIGN.md: the paper's Fig. 4, `K` the data).
RECORD_FIELD_LABELS = {
    "Owner": "Owner (Owner)",
    "Time": "Captured, UTC (Time)",
    "Type": "ROS message type (Type)",
    "Topic": "Topic (Topic)",
}


@dataclass
class Content:
    """What the record page shows of a decrypted record.

    `problem` is set when the record could not be interpreted: then only `raw` (the first
    `raw_shown_bytes` of the plaintext as text) is shown, `raw_truncated` if that is not all.
    """

    document: Any = None
    pretty: str = ""
    size: int = 0
    image_url: str = ""
    image_size: tuple[int | None, int | None] = (None, None)
    odometry: list[tuple[str, str]] = field(default_factory=list)
    is_odometry: bool = False
    ros_seq: int | None = None  # the message's own std_msgs/Header seq, if it has one
    # The paper's record format (Fig. 4) named: its fields but K, labelled, and K, the data.
    fields: list[tuple[str, str]] = field(default_factory=list)
    data_pretty: str = ""
    problem: str = ""
    raw: str = ""
    raw_shown_bytes: int = 0
    raw_truncated: bool = False


def document_parse(plaintext: bytes) -> Any:
    """The record's JSON document. Raises Uninterpretable: not UTF-8, not JSON, nested deeper
    than MAX_DEPTH, an integer of more than MAX_INT_DIGITS digits, NaN, Infinity or 1e999."""
    try:
        text = plaintext.decode("utf-8")
    except UnicodeDecodeError:
        raise Uninterpretable("it is not UTF-8 text") from None
    # A text that cannot break the bounds (_within_bounds) is parsed without a call back per
    # number and without a walk for its depth: the same document, a series' records faster.
    bounded = _within_bounds(plaintext)
    try:
        document = (_BOUNDED_DECODER if bounded else _CHECKING_DECODER).decode(text)
    except RecursionError:
        raise Uninterpretable(f"it is nested more than {MAX_DEPTH} levels deep") from None
    except Uninterpretable:
        raise
    except ValueError as exc:
        raise Uninterpretable(f"it is not JSON ({_printable(str(exc))[:100]})") from None
    if not bounded and _depth_exceeds(document, MAX_DEPTH):
        raise Uninterpretable(f"it is nested more than {MAX_DEPTH} levels deep")
    return document


# Digits as 0, an exponent's sign as +: a run of digits longer than an integer may be, or an
# exponent of three digits or more (the only ways a JSON number overflows a float), is then a
# plain substring (in a string too, where it is harmless).
_NUMBER_SHAPES = bytes.maketrans(b"0123456789E-", b"0000000000e+")
_NUMBER_MAY_BREAK = (b"0" * (MAX_INT_DIGITS + 1), b"e000", b"e+000")


def _within_bounds(plaintext: bytes) -> bool:
    """Whether no number of the text can break a bound and it cannot nest deeper than
    MAX_DEPTH (it opens no more brackets than that): a cheap test, false where unsure."""
    if plaintext.count(b"[") + plaintext.count(b"{") > MAX_DEPTH:
        return False
    shapes = plaintext.translate(_NUMBER_SHAPES)
    return not any(shape in shapes for shape in _NUMBER_MAY_BREAK)


def content_of(*, data_type: str, plaintext: bytes) -> Content:
    """The page's view of a record's plaintext: pretty JSON, its image, its odometry; or, for
    a record that cannot be interpreted, the start of its raw content and why."""
    content = Content(size=len(plaintext))
    try:
        _interpret(content, data_type=data_type, document=document_parse(plaintext))
    except Uninterpretable as exc:
        return _raw_content(plaintext, problem=str(exc))
    except (RecursionError, ValueError, TypeError, OverflowError) as exc:
        # A shape no check above foresaw: the page still answers; the plaintext is not logged.
        logger.warning("a record's content could not be formatted: %s", type(exc).__name__)
        return _raw_content(plaintext, problem="its structure could not be formatted")
    return content


def _interpret(content: Content, *, data_type: str, document: Any) -> None:
    content.document = document
    data = document.get("K") if isinstance(document, dict) else None
    header = data.get("header") if isinstance(data, dict) else None
    seq = header.get("seq") if isinstance(header, dict) else None
    if isinstance(seq, int) and not isinstance(seq, bool):
        content.ros_seq = seq
    shown = document
    if data_type in IMAGE_TYPES and isinstance(data, dict):
        content.image_url = image_data_url(data.get("data"))
        if content.image_url:
            content.image_size = image_size(data.get("width"), data.get("height"))
            length = len(data["data"])
            shown = {**document, "K": {**data, "data": f"<{length} base64 characters, above>"}}
    if data_type == ODOMETRY and isinstance(data, dict):
        content.is_odometry = True
        content.odometry = odometry_rows(data)
    content.pretty = _printable(json.dumps(shown, indent=2, ensure_ascii=False))
    if isinstance(shown, dict) and "K" in shown:
        content.fields = [
            (label, _printable(str(shown[key])))
            for key, label in RECORD_FIELD_LABELS.items()
            if key in shown and isinstance(shown[key], str | int | float)
        ]
        content.data_pretty = _printable(json.dumps(shown["K"], indent=2, ensure_ascii=False))


def _raw_content(plaintext: bytes, *, problem: str) -> Content:
    shown = plaintext[:RAW_SHOWN_BYTES]
    return Content(
        size=len(plaintext),
        problem=problem,
        raw=shown.decode("utf-8", errors="replace"),
        raw_shown_bytes=len(shown),
        raw_truncated=len(plaintext) > len(shown),
    )


def image_data_url(encoded: object) -> str:
    """A data: URL for a base64 PNG or JPEG; empty for anything else."""
    if not isinstance(encoded, str):
        return ""
    try:
        raw = base64.b64decode(encoded, validate=True)
    except (binascii.Error, ValueError):
        return ""
    for magic, mime in _IMAGE_MAGIC.items():
        if raw.startswith(magic):
            return f"data:{mime};base64,{encoded}"
    return ""


def image_size(width: object, height: object) -> tuple[int | None, int | None]:
    """(width, height) for the <img> tag when both are plausible pixel counts, else neither."""
    if _pixels(width) and _pixels(height):
        return width, height
    return None, None


def _pixels(side: object) -> TypeGuard[int]:
    return isinstance(side, int) and not isinstance(side, bool) and 0 < side <= IMAGE_SIDE_MAX


def odometry_rows(data: object) -> list[tuple[str, str]]:
    """(label, value) rows of an odometry record's extracted data (`K`), for any value."""
    data = data if isinstance(data, dict) else {}
    header = data.get("header") if isinstance(data.get("header"), dict) else {}
    stamp = header.get("stamp") if isinstance(header.get("stamp"), dict) else {}
    yaw = _yaw(data.get("orientation"))
    return [
        ("Stamp", _text(stamp.get("iso"))),
        ("Frame", f"{_text(header.get('frame_id'))} to {_text(data.get('child_frame_id'))}"),
        ("Position (m)", _vector(data.get("position"))),
        ("Orientation (quaternion)", _vector(data.get("orientation"), "xyzw")),
        ("Heading (yaw)", MISSING if yaw is None else f"{math.degrees(yaw):.1f}°"),
        ("Linear velocity (m/s)", _vector(data.get("linear_velocity"))),
        ("Angular velocity (rad/s)", _vector(data.get("angular_velocity"))),
    ]


# --- bounded parsing and formatting ------------------------------------------------------


def _bounded_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise Uninterpretable(f"it holds an integer of {digits} digits")
    return int(text)


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise Uninterpretable(f"it holds {_printable(text)[:40]}, which is not a finite number")
    return value


def _no_constant(name: str) -> float:
    raise Uninterpretable(f"it holds {name}, which is not a finite number")


# Made once (json.loads with options makes a decoder per call; a decoder keeps no state
# between calls): a text within the bounds, and one whose numbers are each checked.
_BOUNDED_DECODER = json.JSONDecoder(parse_constant=_no_constant)
_CHECKING_DECODER = json.JSONDecoder(
    parse_constant=_no_constant, parse_int=_bounded_int, parse_float=_finite_float
)


def _depth_exceeds(document: Any, limit: int) -> bool:
    """Whether lists and dicts nest deeper than `limit` (walked without recursion; only
    containers are visited, so a long list of numbers costs one pass over it)."""
    stack = [(document, 1)] if isinstance(document, dict | list) else []
    while stack:
        value, depth = stack.pop()
        if depth > limit:
            return True
        children = value.values() if isinstance(value, dict) else value
        stack.extend((child, depth + 1) for child in children if isinstance(child, dict | list))
    return False


def _printable(text: str) -> str:
    """Text that encodes as UTF-8: a lone surrogate (JSON "\\ud800") becomes its escape."""
    return text.encode("utf-8", errors="backslashreplace").decode("utf-8")


def _finite(value: object) -> float | None:
    """A JSON number as a finite float; None for anything else (bool, huge int, NaN...)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _text(value: object) -> str:
    """A short text or number of the record for the table; MISSING for anything else."""
    if isinstance(value, str) and value:
        return _printable(value[:TEXT_SHOWN_CHARS])
    number = _finite(value)
    return MISSING if number is None else f"{number:g}"


def _number(value: object, digits: int = 4) -> str:
    number = _finite(value)
    return MISSING if number is None else f"{number:.{digits}f}"


def _vector(value: object, names: str = "xyz") -> str:
    if not isinstance(value, dict):
        return MISSING
    return ", ".join(f"{name} {_number(value.get(name))}" for name in names)


def _yaw(orientation: object) -> float | None:
    """Heading about z (radians) of a quaternion dict, or None."""
    if not isinstance(orientation, dict):
        return None
    components = [_finite(orientation.get(name)) for name in "xyzw"]
    if any(c is None for c in components):
        return None
    x, y, z, w = components
    try:
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    except (OverflowError, ValueError):
        return None
    return yaw if math.isfinite(yaw) else None
