"""How a decrypted ROS record is shown: the paper's Fig. 4 JSON, an image, odometry rows, and
the trajectory plot of a topic's poses.

Pure functions of the plaintext the integrity check let through: no request, no database.
"""

import base64
import binascii
import json
import math
from dataclasses import dataclass, field
from typing import Any

ODOMETRY = "nav_msgs/Odometry"
IMAGE_TYPES = {"sensor_msgs/Image", "sensor_msgs/CompressedImage"}
MISSING = "-"
_IMAGE_MAGIC = {b"\x89PNG\r\n\x1a\n": "image/png", b"\xff\xd8\xff": "image/jpeg"}

Pose = tuple[float, float, float | None]


@dataclass
class Content:
    """What the record page shows of a decrypted record."""

    document: Any = None
    pretty: str = ""
    size: int = 0
    image_url: str = ""
    image_size: tuple[int | None, int | None] = (None, None)
    odometry: list[tuple[str, str]] = field(default_factory=list)
    is_odometry: bool = False


def document_parse(plaintext: bytes) -> Any:
    """The record's JSON document, or None if it is not JSON."""
    try:
        return json.loads(plaintext)
    except (ValueError, UnicodeDecodeError):
        return None


def content_of(*, data_type: str, plaintext: bytes) -> Content:
    """The page's view of a record's plaintext: pretty JSON, its image, its odometry."""
    content = Content(size=len(plaintext))
    document = document_parse(plaintext)
    if document is None:
        content.pretty = "(not JSON: download the raw record)"
        return content
    content.document = document
    data = document.get("K") if isinstance(document, dict) else None
    shown = document
    if data_type in IMAGE_TYPES and isinstance(data, dict):
        content.image_url = image_data_url(data.get("data"))
        content.image_size = (data.get("width"), data.get("height"))
        if content.image_url:
            length = len(data.get("data", ""))
            shown = {**document, "K": {**data, "data": f"<{length} base64 characters, above>"}}
    if data_type == ODOMETRY and isinstance(data, dict):
        content.is_odometry = True
        content.odometry = odometry_rows(data)
    content.pretty = json.dumps(shown, indent=2, ensure_ascii=False)
    return content


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


def odometry_rows(data: dict) -> list[tuple[str, str]]:
    """(label, value) rows of an odometry record's extracted data (`K`)."""
    header = data.get("header") if isinstance(data.get("header"), dict) else {}
    stamp = header.get("stamp") if isinstance(header.get("stamp"), dict) else {}
    yaw = _yaw(data.get("orientation"))
    child_frame = data.get("child_frame_id") or MISSING
    return [
        ("Stamp", str(stamp.get("iso", MISSING))),
        ("Frame", f"{header.get('frame_id') or MISSING} to {child_frame}"),
        ("Position (m)", _vector(data.get("position"))),
        ("Orientation (quaternion)", _vector(data.get("orientation"), "xyzw")),
        ("Heading (yaw)", MISSING if yaw is None else f"{math.degrees(yaw):.1f}°"),
        ("Linear velocity (m/s)", _vector(data.get("linear_velocity"))),
        ("Angular velocity (rad/s)", _vector(data.get("angular_velocity"))),
    ]


def pose_of(plaintext: bytes) -> Pose | None:
    """(x, y, yaw) of an odometry record's plaintext, or None."""
    document = document_parse(plaintext)
    data = document.get("K") if isinstance(document, dict) else None
    position = data.get("position") if isinstance(data, dict) else None
    if not isinstance(position, dict):
        return None
    x, y = position.get("x"), position.get("y")
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in (x, y)):
        return None
    return float(x), float(y), _yaw(data.get("orientation"))


def trajectory_plot(poses: list[Pose]) -> dict[str, object]:
    """Screen coordinates of the poses on a square-scaled plot (y up), for trajectory.svg."""
    width, height, margin = 480, 360, 36
    if not poses:
        return {"width": width, "height": height, "points": "", "count": 0}
    xs, ys = [p[0] for p in poses], [p[1] for p in poses]
    span = max(max(xs) - min(xs), max(ys) - min(ys), 0.5)
    scale = min(width - 2 * margin, height - 2 * margin) / span
    cx, cy = (max(xs) + min(xs)) / 2, (max(ys) + min(ys)) / 2

    def screen(x: float, y: float) -> tuple[float, float]:
        return round(width / 2 + (x - cx) * scale, 1), round(height / 2 - (y - cy) * scale, 1)

    points = [screen(x, y) for x, y, _ in poses]
    last_x, last_y, yaw = poses[-1]
    end = points[-1]
    arrow = None
    if yaw is not None:
        arrow = (round(end[0] + 22 * math.cos(yaw), 1), round(end[1] - 22 * math.sin(yaw), 1))
    return {
        "width": width,
        "height": height,
        "points": " ".join(f"{x},{y}" for x, y in points),
        "start": points[0],
        "end": end,
        "arrow": arrow,
        "count": len(poses),
        "x_range": f"{min(xs):.2f} … {max(xs):.2f}",
        "y_range": f"{min(ys):.2f} … {max(ys):.2f}",
        "last": f"{last_x:.2f}, {last_y:.2f}",
    }


def _number(value: object, digits: int = 4) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return MISSING
    return f"{value:.{digits}f}"


def _vector(value: object, names: str = "xyz") -> str:
    if not isinstance(value, dict):
        return MISSING
    return ", ".join(f"{name} {_number(value.get(name))}" for name in names)


def _yaw(orientation: object) -> float | None:
    """Heading about z (radians) of a quaternion dict, or None."""
    if not isinstance(orientation, dict):
        return None
    try:
        x, y, z, w = (float(orientation[name]) for name in "xyzw")
    except (KeyError, TypeError, ValueError):
        return None
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
