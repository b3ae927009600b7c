"""How a decrypted ROS record is shown: the paper's Fig. 4 JSON, an image, odometry rows, and
the trajectory plot of a topic's poses.

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
from collections.abc import Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
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
# Metres from the origin a plotted position may be: further is no robot's position.
POSE_LIMIT = 1e9
# Pixels an image's declared width or height may have to be used as the <img> size.
IMAGE_SIDE_MAX = 100_000

Pose = tuple[float, float, float | None]


class Uninterpretable(ValueError):
    """A record's plaintext that is not JSON the pages can show; the message says why."""


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
    try:
        document = json.loads(
            text,
            parse_int=_bounded_int,
            parse_float=_finite_float,
            parse_constant=_no_constant,
        )
    except RecursionError:
        raise Uninterpretable(f"it is nested more than {MAX_DEPTH} levels deep") from None
    except Uninterpretable:
        raise
    except ValueError as exc:
        raise Uninterpretable(f"it is not JSON ({_printable(str(exc))[:100]})") from None
    if _depth_exceeds(document, MAX_DEPTH):
        raise Uninterpretable(f"it is nested more than {MAX_DEPTH} levels deep")
    return document


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


def pose_of(plaintext: bytes) -> Pose | None:
    """(x, y, yaw) of an odometry record's plaintext, or None if it has no plottable pose."""
    try:
        document = document_parse(plaintext)
    except Uninterpretable:
        return None
    data = document.get("K") if isinstance(document, dict) else None
    position = data.get("position") if isinstance(data, dict) else None
    if not isinstance(position, dict):
        return None
    x, y = _coordinate(position.get("x")), _coordinate(position.get("y"))
    if x is None or y is None:
        return None
    return x, y, _yaw(data.get("orientation"))


def trajectory_plot(
    poses: Sequence[Pose | None], *, times: Sequence[datetime] | None = None
) -> dict[str, object]:
    """Screen coordinates of the poses on a square-scaled plot (y up) with axes in metres and
    the first and last capture times (`times`, one per pose, if given), for trajectory.svg.

    Poses that cannot be plotted (None, a coordinate that is not a finite number within
    POSE_LIMIT) are left out and counted as `skipped`.
    """
    width, height = PLOT_WIDTH, PLOT_HEIGHT
    left, right, top, bottom = 64, 20, 40, 56
    kept = [
        (pose, times[index] if times is not None else None)
        for index, pose in enumerate(map(_plottable, poses))
        if pose is not None
    ]
    plotted = [pose for pose, _ in kept]
    skipped = len(poses) - len(plotted)
    if not plotted:
        return {"width": width, "height": height, "points": "", "count": 0, "skipped": skipped}
    xs, ys = [p[0] for p in plotted], [p[1] for p in plotted]
    area_w, area_h = width - left - right, height - top - bottom
    span = max(max(xs) - min(xs), max(ys) - min(ys), 0.5) * 1.1
    scale = min(area_w, area_h) / span
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2
    mid_x, mid_y = left + area_w / 2, top + area_h / 2

    def screen(x: float, y: float) -> tuple[float, float]:
        return round(mid_x + (x - cx) * scale, 1), round(mid_y - (y - cy) * scale, 1)

    points = [screen(x, y) for x, y, _ in plotted]
    last_x, last_y, yaw = plotted[-1]
    end = points[-1]
    arrow = None
    if yaw is not None:
        arrow = (round(end[0] + 22 * math.cos(yaw), 1), round(end[1] - 22 * math.sin(yaw), 1))
    shown_x = (cx - (area_w / 2) / scale, cx + (area_w / 2) / scale)
    shown_y = (cy - (area_h / 2) / scale, cy + (area_h / 2) / scale)
    plot: dict[str, object] = {
        "width": width,
        "height": height,
        "points": " ".join(f"{x},{y}" for x, y in points),
        "start": points[0],
        "end": end,
        "arrow": arrow,
        "count": len(plotted),
        "skipped": skipped,
        "x_range": f"{min(xs):.2f} … {max(xs):.2f}",
        "y_range": f"{min(ys):.2f} … {max(ys):.2f}",
        "last": f"{last_x:.2f}, {last_y:.2f}",
        "axes": {"left": left, "right": width - right, "top": top, "bottom": height - bottom},
        "x_ticks": [(screen(t, cy)[0], label) for t, label in _ticks(*shown_x)],
        "y_ticks": [(screen(cx, t)[1], label) for t, label in _ticks(*shown_y)],
    }
    first_time, last_time = kept[0][1], kept[-1][1]
    if first_time is not None and last_time is not None:
        plot["first_time"] = _plot_time(first_time)
        plot["last_time"] = _plot_time(last_time)
    return plot


PLOT_WIDTH, PLOT_HEIGHT = 640, 480


def _ticks(low: float, high: float, *, wanted: int = 5) -> list[tuple[float, str]]:
    """Round axis values (1, 2 or 5 times a power of ten apart) within [low, high]."""
    raw = (high - low) / wanted
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    decimals = max(0, -math.floor(math.log10(step)))
    first = math.ceil(low / step)
    return [
        (value, f"{value:.{decimals}f}")
        for value in (n * step for n in range(first, math.floor(high / step) + 1))
    ]


def _plot_time(moment: datetime) -> str:
    return moment.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]


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


def _depth_exceeds(document: Any, limit: int) -> bool:
    """Whether lists and dicts nest deeper than `limit` (walked without recursion)."""
    stack = [(document, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict):
            children = value.values()
        elif isinstance(value, list):
            children = value
        else:
            continue
        if depth > limit:
            return True
        stack.extend((child, depth + 1) for child in children)
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


def _coordinate(value: object) -> float | None:
    number = _finite(value)
    return number if number is not None and abs(number) <= POSE_LIMIT else None


def _plottable(pose: object) -> Pose | None:
    if not isinstance(pose, tuple) or len(pose) != 3:
        return None
    x, y = _coordinate(pose[0]), _coordinate(pose[1])
    if x is None or y is None:
        return None
    return x, y, _finite(pose[2])


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
