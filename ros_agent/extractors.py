"""ROS messages to JSON-able dicts: the `K` of the paper's Fig. 4 record.

One function per message type, chosen by `extract(msg, ros_type)`; any other type goes
through `message_to_dict`, a generic walk of the message's fields. Times are
`{"secs", "nsecs", "iso"}`, durations `{"secs", "nsecs"}`, byte arrays base64, and floats
that JSON cannot hold (NaN, infinities) become null.
"""

import base64
import io
import math
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
from PIL import Image

try:
    import genpy
except ImportError:  # a ROS 2 robot has no ROS 1; its messages come through ros_agent.ros2msg
    genpy = None

JsonDict = dict[str, Any]
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


class ExtractionError(ValueError):
    """The message cannot be turned into a record (e.g. an image encoding we do not read)."""


# The channels of a PNG are red, green, blue (and alpha): an encoding whose array holds them in
# another order is reordered (the same permutation both ways).
BGR_ORDER = (2, 1, 0)
BGRA_ORDER = (2, 1, 0, 3)
# ROS image encoding -> (numpy element type, channels, order of its channels in the PNG or None)
IMAGE_ENCODINGS: dict[str, tuple[type[np.unsignedinteger], int, tuple[int, ...] | None]] = {
    "rgb8": (np.uint8, 3, None),
    "bgr8": (np.uint8, 3, BGR_ORDER),
    "rgba8": (np.uint8, 4, None),
    "bgra8": (np.uint8, 4, BGRA_ORDER),
    "mono8": (np.uint8, 1, None),
    "8UC1": (np.uint8, 1, None),
    "mono16": (np.uint16, 1, None),
    "16UC1": (np.uint16, 1, None),
}
# zlib's level: its fastest, as OpenCV's PNG default (the agent's CPU, not the bytes, is short)
PNG_COMPRESS_LEVEL = 1


def extract(msg: Any, ros_type: str) -> JsonDict:
    """The record data `K` of `msg`, whose ROS type is `ros_type` (e.g. nav_msgs/Odometry)."""
    extractor = EXTRACTORS.get(ros_type, message_to_dict)
    return extractor(msg)


def odometry(msg: Any) -> JsonDict:
    """nav_msgs/Odometry: pose and twist with their covariances, frames and stamp."""
    pose, twist = msg.pose, msg.twist
    return {
        "header": header(msg.header),
        "child_frame_id": msg.child_frame_id,
        "position": _vector(pose.pose.position),
        "orientation": _quaternion(pose.pose.orientation),
        "linear_velocity": _vector(twist.twist.linear),
        "angular_velocity": _vector(twist.twist.angular),
        "pose_covariance": _floats(pose.covariance),
        "twist_covariance": _floats(twist.covariance),
    }


def image(msg: Any) -> JsonDict:
    """sensor_msgs/Image: the pixels as a lossless PNG (base64), with size and encoding."""
    return {
        "header": header(msg.header),
        "width": msg.width,
        "height": msg.height,
        "encoding": msg.encoding,
        "format": "png",
        "data": _b64(encode_png(image_to_array(msg), msg.encoding)),
    }


def compressed_image(msg: Any) -> JsonDict:
    """sensor_msgs/CompressedImage: the bytes as they came (jpeg, png, ...), base64."""
    return {"header": header(msg.header), "format": msg.format, "data": _b64(_bytes(msg.data))}


def imu(msg: Any) -> JsonDict:
    """sensor_msgs/Imu: orientation, angular velocity, linear acceleration, covariances."""
    return {
        "header": header(msg.header),
        "orientation": _quaternion(msg.orientation),
        "orientation_covariance": _floats(msg.orientation_covariance),
        "angular_velocity": _vector(msg.angular_velocity),
        "angular_velocity_covariance": _floats(msg.angular_velocity_covariance),
        "linear_acceleration": _vector(msg.linear_acceleration),
        "linear_acceleration_covariance": _floats(msg.linear_acceleration_covariance),
    }


def string(msg: Any) -> JsonDict:
    """std_msgs/String."""
    return {"data": msg.data}


EXTRACTORS: dict[str, Callable[[Any], JsonDict]] = {
    "nav_msgs/Odometry": odometry,
    "sensor_msgs/Image": image,
    "sensor_msgs/CompressedImage": compressed_image,
    "sensor_msgs/Imu": imu,
    "std_msgs/String": string,
}


def image_to_array(msg: Any) -> np.ndarray:
    """The pixels of a sensor_msgs/Image as a (height, width[, channels]) array in native order.

    Rows may be padded (`step` above width * pixel size) and 16-bit data big-endian.
    """
    encoding = msg.encoding
    if encoding not in IMAGE_ENCODINGS:
        raise ExtractionError(
            f"image encoding {encoding!r} is not supported; supported: {', '.join(IMAGE_ENCODINGS)}"
        )
    element, channels, _ = IMAGE_ENCODINGS[encoding]
    dtype = np.dtype(element).newbyteorder(">" if msg.is_bigendian else "<")
    height, width, step = msg.height, msg.width, msg.step
    row_bytes = width * channels * dtype.itemsize
    if height == 0 or width == 0:
        raise ExtractionError(f"image is empty ({width}x{height})")
    if step < row_bytes:
        raise ExtractionError(
            f"image step {step} is below width * pixel size = {row_bytes} for {encoding}"
        )
    data = _bytes(msg.data)
    if len(data) < height * step:
        raise ExtractionError(
            f"image data has {len(data)} bytes, {height} rows of step {step} need {height * step}"
        )
    rows = np.frombuffer(data, dtype=np.uint8, count=height * step).reshape(height, step)
    pixels = np.ascontiguousarray(rows[:, :row_bytes]).view(dtype).astype(element)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return pixels.reshape(shape)


def encode_png(pixels: np.ndarray, encoding: str) -> bytes:
    """PNG bytes of an array from `image_to_array`, colours stored in their true order (RGB,
    RGBA, 8-bit grey or 16-bit grey)."""
    order = IMAGE_ENCODINGS[encoding][2]
    if order is not None:
        pixels = pixels[..., list(order)]
    if pixels.dtype == np.uint16:
        # Pillow's 16-bit grey is little-endian in memory, whatever the machine's order
        pixels = pixels.astype("<u2")
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(pixels)).save(
        out, format="PNG", compress_level=PNG_COMPRESS_LEVEL
    )
    return out.getvalue()


def message_to_dict(msg: Any) -> JsonDict:
    """Any genpy message, field by field (`__slots__` and `_slot_types`), recursively.

    A message that walks itself (a ROS 2 one through ros_agent.ros2msg) gives `as_record()`.
    """
    as_record = getattr(msg, "as_record", None)
    if as_record is not None:
        return as_record()
    return {
        name: _field(getattr(msg, name), slot_type)
        for name, slot_type in zip(msg.__slots__, msg._slot_types, strict=True)
    }


def header(value: Any) -> JsonDict:
    """std_msgs/Header: seq, stamp (secs, nsecs, ISO 8601 UTC) and frame id."""
    return {"seq": value.seq, "stamp": _time(value.stamp), "frame_id": value.frame_id}


def stamp_datetime(stamp: Any) -> datetime:
    """A ROS time as an aware UTC datetime (microsecond precision)."""
    micros = stamp.secs * 1_000_000 + stamp.nsecs // 1000
    return _EPOCH + timedelta(microseconds=micros)


def iso_utc(moment: datetime) -> str:
    """ISO 8601 UTC with microseconds and a Z, as envelope headers carry it."""
    return moment.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def _field(value: Any, slot_type: str) -> Any:
    if genpy is None:
        raise ExtractionError("genpy (ROS 1) is not installed")
    if isinstance(value, genpy.Message):
        return message_to_dict(value)
    if isinstance(value, genpy.Time):
        return _time(value)
    if isinstance(value, genpy.Duration):
        return {"secs": value.secs, "nsecs": value.nsecs}
    if isinstance(value, bytes | bytearray):
        return _b64(bytes(value))
    if isinstance(value, list | tuple):
        element_type = slot_type.split("[", 1)[0]
        if element_type in ("uint8", "char"):
            return _b64(bytes(value))
        return [_field(item, element_type) for item in value]
    if isinstance(value, float):
        return _finite(value)
    return value


def _time(stamp: Any) -> JsonDict:
    return {
        "secs": stamp.secs,
        "nsecs": stamp.nsecs,
        "iso": iso_utc(stamp_datetime(stamp)),
    }


def _vector(value: Any) -> JsonDict:
    return {"x": _finite(value.x), "y": _finite(value.y), "z": _finite(value.z)}


def _quaternion(value: Any) -> JsonDict:
    return {**_vector(value), "w": _finite(value.w)}


def _floats(values: Any) -> list[float | None]:
    return [_finite(value) for value in values]


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _bytes(data: Any) -> bytes:
    # rospy gives bytes for uint8[]; a message built in Python may hold a list of ints
    return data if isinstance(data, bytes) else bytes(data)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")
