"""What MCAP message each exported record becomes, from its sealed plaintext alone.

The portal writes an export's messages by these rules (sharing/mcap_export.py), and the check
rebuilds a signed record's message by them from the plaintext its robot signed: the message in
the MCAP file must be that message byte for byte (docs/export.md), so one module holds them.

`ros2msg` schemas and `cdr` messages serialised by rosbags (as the ROS 2 agent reads them). The
records' `K` is what ros_agent's extractors made of a message (ros_agent/extractors.py,
ros_agent/ros2msg.py): nav_msgs/Odometry, sensor_msgs/Image (PNG), CompressedImage and Imu
have their own shape and are rebuilt here field by field; any other type was walked field by
field and is rebuilt from rosbags' ROS 2 Humble definition of it. What cannot be rebuilt (a
type rosbags does not know, a record whose fields do not fit the type, a plaintext that is not
JSON) becomes a `json` message: its Fig. 4 record as it was sealed.

Pure functions of a record's type and plaintext: no request, no database, no portal.
"""

import base64
import binascii
import io
import json
import math
import re
import struct
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from PIL import Image
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

JSON_SCHEMA = b'{"type": "object", "description": "an AuthROS Fig. 4 record"}'
# A plaintext is read as JSON within these bounds (sharing/content.py reads it by the same).
MAX_DEPTH = 64
MAX_INT_DIGITS = 30
_HEADER = "std_msgs/msg/Header"
_TIME_TYPES = ("builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration")
_NUMPY_TYPES = {
    "bool": np.bool_,
    "byte": np.uint8,
    "char": np.uint8,
    "int8": np.int8,
    "uint8": np.uint8,
    "int16": np.int16,
    "uint16": np.uint16,
    "int32": np.int32,
    "uint32": np.uint32,
    "int64": np.int64,
    "uint64": np.uint64,
    "float32": np.float32,
    "float64": np.float64,
}
# The range of each ROS integer type: a value outside it does not fit the type (issue 38).
_INTEGER_RANGES = {
    name: (int(np.iinfo(kind).min), int(np.iinfo(kind).max))
    for name, kind in _NUMPY_TYPES.items()
    if name not in ("bool", "float32", "float64")
}
_FLOAT32_MAX = float(np.finfo(np.float32).max)
# An image decoded back into pixels holds at most this many bytes; a larger one (or a PNG
# whose own size is not the record's) goes on a JSON channel, so that a small PNG that
# inflates to gigabytes cannot take the worker's memory.
MAX_IMAGE_BYTES = 64 * 1024 * 1024
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# ROS image encoding -> (element type, channels, order of its channels in the PNG or None,
# the PNG's bit depth and colour type as the agent writes them: ros_agent/extractors.py)
_IMAGE_ENCODINGS: dict[str, tuple[type, int, tuple[int, ...] | None, tuple[int, int]]] = {
    "rgb8": (np.uint8, 3, None, (8, 2)),
    "bgr8": (np.uint8, 3, (2, 1, 0), (8, 2)),
    "rgba8": (np.uint8, 4, None, (8, 6)),
    "bgra8": (np.uint8, 4, (2, 1, 0, 3), (8, 6)),
    "mono8": (np.uint8, 1, None, (8, 0)),
    "8UC1": (np.uint8, 1, None, (8, 0)),
    "mono16": (np.uint16, 1, None, (16, 0)),
    "16UC1": (np.uint16, 1, None, (16, 0)),
}


class Unbuildable(ValueError):
    """A record's data does not fit its ROS type: it goes on a JSON channel instead."""


@dataclass(frozen=True)
class EncodedMessage:
    """One record as an MCAP message: its schema, its encoding and its bytes."""

    schema_name: str
    schema_encoding: str  # "ros2msg" or "jsonschema"
    schema: bytes
    message_encoding: str  # "cdr" or "json"
    data: bytes
    stamp_ns: int | None  # the message header's stamp, when it has one


@cache
def typestore() -> Typestore:
    return get_typestore(Stores.ROS2_HUMBLE)


def ros2_type_name(data_type: str) -> str:
    """`nav_msgs/Odometry` -> `nav_msgs/msg/Odometry` (ROS 2 names pass unchanged)."""
    if data_type.count("/") >= 2:
        return data_type
    package, _, name = data_type.partition("/")
    return f"{package}/msg/{name}"


def message_encode(*, data_type: str, plaintext: bytes) -> EncodedMessage:
    """The record as a CDR message of its ROS 2 type, or its Fig. 4 record as JSON."""
    document = document_of(plaintext)
    msgtype = ros2_type_name(data_type)
    data = document.get("K") if isinstance(document, dict) else None
    try:
        if msgtype not in typestore().types:
            raise Unbuildable(f"{msgtype} is not a ROS 2 Humble type")
        encoder = _ENCODERS.get(msgtype)
        if encoder is not None:
            encoded = encoder(data)
        else:
            message = _BUILDERS.get(msgtype, _generic)(msgtype, data)
            encoded = typestore().serialize_cdr(message, msgtype)
    except (
        Unbuildable,
        TypeError,
        ValueError,
        OverflowError,
        KeyError,
        AttributeError,
        IndexError,
        struct.error,
    ):
        # What does not fit its type (issue 38: one hostile record must not fail an export).
        return _json_message(data_type, document, plaintext)
    return EncodedMessage(
        msgtype, "ros2msg", _ros2_schema(msgtype), "cdr", bytes(encoded), _stamp_ns(data)
    )


def message_log_time(message: EncodedMessage, captured_ns: int) -> int:
    """The message's log and publish time: its header's stamp to the nanosecond when that is
    the capture time (the envelope keeps microseconds), else the capture time."""
    stamp = message.stamp_ns
    return stamp if stamp is not None and stamp // 1000 == captured_ns // 1000 else captured_ns


def schema_of(*, schema_name: str, message_encoding: str) -> tuple[str, bytes] | None:
    """(schema encoding, schema data) an export writes for a message of this schema and
    encoding; None for a pair it never writes."""
    if message_encoding == "json":
        return "jsonschema", JSON_SCHEMA
    if message_encoding == "cdr" and schema_name in typestore().types:
        return "ros2msg", _ros2_schema(schema_name)
    return None


def _json_message(data_type: str, document: Any, plaintext: bytes) -> EncodedMessage:
    if document is None:  # not JSON: its bytes, base64, in a JSON object
        body = json.dumps({"raw_base64": base64.b64encode(plaintext).decode()}).encode()
    else:
        body = bytes(plaintext)
    data = document.get("K") if isinstance(document, dict) else None
    return EncodedMessage(data_type, "jsonschema", JSON_SCHEMA, "json", body, _stamp_ns(data))


@cache
def _ros2_schema(msgtype: str) -> bytes:
    return typestore().generate_msgdef(msgtype, ros_version=2)[0].encode()


# --- the plaintext as JSON -------------------------------------------------------------------


def document_of(plaintext: bytes) -> Any:
    """The record's JSON document, or None when it is not one: not UTF-8, not JSON, nested
    deeper than MAX_DEPTH, an integer of more than MAX_INT_DIGITS digits, NaN, Infinity or
    1e999 (the rules the record page reads plaintexts by, sharing/content.py)."""
    try:
        text = bytes(plaintext).decode("utf-8")
    except UnicodeDecodeError:
        return None
    # json.loads recurses in C, and web3 raises the recursion limit: count the depth first.
    if _depth_exceeds(text, MAX_DEPTH):
        return None
    try:
        if not _numeral_to_check(bytes(plaintext)):
            # No integer of more than MAX_INT_DIGITS digits, no number beyond a float's range
            # (that needs 100 or more digits in a row, or an exponent of three digits): the
            # parser's own numbers are the checked ones, without a call per number.
            return json.loads(text, parse_constant=_no_constant)
        return json.loads(
            text, parse_int=_bounded_int, parse_float=_finite_float, parse_constant=_no_constant
        )
    except (ValueError, RecursionError):
        return None


# Where a numeral may be too long or too large, each number is checked as it is parsed: a run
# of MAX_INT_DIGITS + 1 digits, or an exponent of three digits (`[eE][+-]?[0-9]{3}`), found
# with the bytes translated (digits to 0, E to e, - to +) and searched for as plain substrings,
# a tenth of the regular expression's time on a record of a kilobyte.
_NUMERAL_CLASSES = bytes.maketrans(b"0123456789E-", b"0000000000e+")
_NUMERALS_TO_CHECK = (b"0" * (MAX_INT_DIGITS + 1), b"e000", b"e+000")


def _numeral_to_check(raw: bytes) -> bool:
    """Whether the UTF-8 text may hold a numeral too long or too large for the parser's own
    numbers (its ASCII bytes are its ASCII characters: no other byte of UTF-8 is below 128)."""
    classes = raw.translate(_NUMERAL_CLASSES)
    return any(found in classes for found in _NUMERALS_TO_CHECK)


_JSON_ESCAPE = re.compile(r"\\.", re.DOTALL)
_JSON_STRING = re.compile(r'"[^"]*"')


def _depth_exceeds(text: str, limit: int) -> bool:
    """Whether the brackets outside JSON strings nest deeper than `limit` (linear time)."""
    if text.count("[") + text.count("{") <= limit:
        return False
    depth = 0
    for character in _JSON_STRING.sub("", _JSON_ESCAPE.sub("", text)):
        if character in "[{":
            depth += 1
            if depth > limit:
                return True
        elif character in "]}":
            depth -= 1
    return False


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise ValueError("an integer of too many digits")
    return int(text)


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a finite number")


# --- the types the extractors shape themselves -----------------------------------------------


# An Odometry's CDR written directly (little endian, rosbags' layout byte for byte; the tests
# compare the two): most of a robot's records are odometry, and building rosbags' message
# objects for each cost most of its encoding (issue 45).
_CDR_HEADER = b"\x00\x01\x00\x00"
_ODOMETRY_STAMP = struct.Struct("<iI")
_ODOMETRY_NUMBERS = struct.Struct("<85d")  # pose 7, covariance 36, twist 6, covariance 36
_UINT32 = struct.Struct("<I")


def _odometry_cdr(data: Any) -> bytes:
    """The CDR of nav_msgs/msg/Odometry from the extractor's shape (what rosbags makes of the
    message built from it); Unbuildable (or a ValueError) where the record does not fit."""
    data = _object(data)
    header = _object(data.get("header"))
    stamp = _object(header.get("stamp"))
    secs, nsecs = _integer(stamp.get("secs")), _integer(stamp.get("nsecs"))
    if not (-(2**31) <= secs < 2**31 and 0 <= nsecs < 10**9):
        raise Unbuildable("a time out of the range ROS 2 holds")
    position = _object(data.get("position"))
    orientation = _object(data.get("orientation"))
    linear = _object(data.get("linear_velocity"))
    angular = _object(data.get("angular_velocity"))
    numbers = [
        *(_float(position.get(name)) for name in "xyz"),
        *(_float(orientation.get(name)) for name in "xyzw"),
        *_float_list(data.get("pose_covariance"), 36),
        *(_float(linear.get(name)) for name in "xyz"),
        *(_float(angular.get(name)) for name in "xyz"),
        *_float_list(data.get("twist_covariance"), 36),
    ]
    out = bytearray(_CDR_HEADER)
    out += _ODOMETRY_STAMP.pack(secs, nsecs)
    for text in (_text(header.get("frame_id")), _text(data.get("child_frame_id"))):
        raw = text.encode()
        out += bytes(-(len(out) - 4) % 4)  # aligned to 4 from the end of the CDR header
        out += _UINT32.pack(len(raw) + 1) + raw + b"\x00"
    out += bytes(-(len(out) - 4) % 8)
    out += _ODOMETRY_NUMBERS.pack(*numbers)
    return bytes(out)


def _float_list(value: Any, length: int) -> list[float]:
    """`_floats` as plain floats (what numpy's float64 array holds, value for value)."""
    items = _list(value)
    if len(items) != length:
        raise Unbuildable(f"{len(items)} values where {length} belong")
    return [item if type(item) is float else _float(item) for item in items]


def _imu(msgtype: str, data: Any) -> Any:
    data = _object(data)
    return typestore().types[msgtype](
        header=_header(data.get("header")),
        orientation=_quaternion(data.get("orientation")),
        orientation_covariance=_floats(data.get("orientation_covariance"), 9),
        angular_velocity=_vector3(data.get("angular_velocity")),
        angular_velocity_covariance=_floats(data.get("angular_velocity_covariance"), 9),
        linear_acceleration=_vector3(data.get("linear_acceleration")),
        linear_acceleration_covariance=_floats(data.get("linear_acceleration_covariance"), 9),
    )


def _compressed_image(msgtype: str, data: Any) -> Any:
    data = _object(data)
    return typestore().types[msgtype](
        header=_header(data.get("header")),
        format=_text(data.get("format")),
        data=np.frombuffer(_base64(data.get("data")), dtype=np.uint8),
    )


def _image(msgtype: str, data: Any) -> Any:
    """The PNG the extractor made, decoded back into the pixels of the original encoding."""
    data = _object(data)
    encoding = _text(data.get("encoding"))
    if encoding not in _IMAGE_ENCODINGS or data.get("format") != "png":
        raise Unbuildable(f"image encoding {encoding!r} is not one the agent stores")
    element, channels, order, kind = _IMAGE_ENCODINGS[encoding]
    width, height = _integer(data.get("width")), _integer(data.get("height"))
    if width <= 0 or height <= 0:
        raise Unbuildable("an image of no pixels")
    if width * height * channels * np.dtype(element).itemsize > MAX_IMAGE_BYTES:
        raise Unbuildable(f"an image of more than {MAX_IMAGE_BYTES} bytes")
    encoded = _base64(data.get("data"))
    if _png_size(encoded) != (width, height):
        raise Unbuildable("the PNG's own size is not the record's")
    if encoded[24:26] != bytes(kind):  # IHDR's bit depth and colour type
        raise Unbuildable(f"the PNG's pixels are not those of {encoding}")
    try:
        with Image.open(io.BytesIO(encoded), formats=["PNG"]) as png:
            pixels = np.asarray(png)
    except (OSError, ValueError, SyntaxError) as exc:  # what Pillow raises for a broken PNG
        raise Unbuildable("the image is not a PNG") from exc
    if order is not None and pixels.ndim == 3:
        pixels = pixels[..., list(order)]
    expected = (height, width) if channels == 1 else (height, width, channels)
    if pixels.shape != expected or pixels.dtype != element:
        raise Unbuildable(f"the PNG is {pixels.shape} {pixels.dtype}, not {expected} {encoding}")
    raw = np.ascontiguousarray(pixels).astype(np.dtype(element).newbyteorder("<")).tobytes()
    return typestore().types[msgtype](
        header=_header(data.get("header")),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels * np.dtype(element).itemsize,
        data=np.frombuffer(raw, dtype=np.uint8),
    )


def _png_size(png: bytes) -> tuple[int, int] | None:
    """(width, height) its IHDR chunk states, read before anything is decoded."""
    if len(png) < 24 or not png.startswith(_PNG_SIGNATURE) or png[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", png[16:24])
    return width, height


# --- any other type, from its definition -----------------------------------------------------


def _generic(msgtype: str, data: Any) -> Any:
    """A message of `msgtype` from the generic walk's dict (ros_agent.ros2msg._message_dict)."""
    if msgtype == _HEADER:
        return _header(data)
    if msgtype in _TIME_TYPES:
        return _time(data, msgtype)
    data = _object(data)
    _consts, fields = typestore().fielddefs[msgtype]
    values = {name: _field(definition, data.get(name)) for name, definition in fields}
    return typestore().types[msgtype](**values)


def _field(definition: tuple, value: Any) -> Any:
    kind, detail = definition
    kind = int(kind)
    if kind == 2:  # NAME: a nested message
        return _generic(detail, value)
    if kind == 1:  # BASE: a primitive or a string
        return _primitive(detail[0], value)
    (element_kind, element_detail), length = detail  # 3 ARRAY, 4 SEQUENCE
    if int(element_kind) == 1 and element_detail[0] in ("uint8", "byte", "char"):
        raw = _base64(value) if isinstance(value, str) else bytes(_list(value))
        if kind == 3 and len(raw) != length:
            raise Unbuildable(f"{len(raw)} bytes where {length} belong")
        return np.frombuffer(raw, dtype=np.uint8)
    items = _list(value)
    if kind == 3 and len(items) != length:
        raise Unbuildable(f"{len(items)} values where {length} belong")
    if int(element_kind) == 1 and element_detail[0] in _NUMPY_TYPES:
        name = element_detail[0]
        return np.array([_primitive(name, item) for item in items], dtype=_NUMPY_TYPES[name])
    return [_field((element_kind, element_detail), item) for item in items]


def _primitive(name: str, value: Any) -> Any:
    if name in ("string", "wstring"):
        return _text(value)
    if name in ("float32", "float64"):
        number = _float(value)
        if name == "float32" and math.isfinite(number) and abs(number) > _FLOAT32_MAX:
            raise Unbuildable("a float32 field holds a number beyond its range")
        return number
    if name == "bool":
        if not isinstance(value, bool):
            raise Unbuildable("a bool field holds something else")
        return value
    number = _integer(value)
    low, high = _INTEGER_RANGES[name]
    if not low <= number <= high:
        raise Unbuildable(f"an {name} field holds {number}, outside its range")
    return number


# --- shared pieces ---------------------------------------------------------------------------


def _header(value: Any) -> Any:
    value = _object(value)
    return typestore().types[_HEADER](
        stamp=_time(value.get("stamp"), "builtin_interfaces/msg/Time"),
        frame_id=_text(value.get("frame_id")),
    )


def _time(value: Any, msgtype: str) -> Any:
    value = _object(value)
    secs, nsecs = _integer(value.get("secs")), _integer(value.get("nsecs"))
    if not (-(2**31) <= secs < 2**31 and 0 <= nsecs < 10**9):
        raise Unbuildable("a time out of the range ROS 2 holds")
    return typestore().types[msgtype](sec=secs, nanosec=nsecs)


def _stamp_ns(data: Any) -> int | None:
    """The message header's stamp in nanoseconds, if it has a valid one."""
    try:
        stamp = _object(_object(data).get("header")).get("stamp")
        secs, nsecs = _integer(_object(stamp).get("secs")), _integer(stamp.get("nsecs"))
    except Unbuildable:
        return None
    return secs * 10**9 + nsecs if secs >= 0 and 0 <= nsecs < 10**9 else None


def _vector3(value: Any) -> Any:
    value = _object(value)
    return typestore().types["geometry_msgs/msg/Vector3"](
        x=_float(value.get("x")), y=_float(value.get("y")), z=_float(value.get("z"))
    )


def _quaternion(value: Any) -> Any:
    value = _object(value)
    return typestore().types["geometry_msgs/msg/Quaternion"](
        x=_float(value.get("x")),
        y=_float(value.get("y")),
        z=_float(value.get("z")),
        w=_float(value.get("w")),
    )


def _floats(value: Any, length: int) -> np.ndarray:
    items = _list(value)
    if len(items) != length:
        raise Unbuildable(f"{len(items)} values where {length} belong")
    if not all(type(item) is float or type(item) is int for item in items):
        items = [_float(item) for item in items]  # null, or what no number is (a bool too)
    return np.array(items, dtype=np.float64)


def _float(value: Any) -> float:
    """A JSON number; null is what the extractors made of NaN and the infinities."""
    if value is None:
        return math.nan
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise Unbuildable("a number field holds something else")
    return float(value)


def _integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise Unbuildable("an integer field holds something else")
    return value


def _text(value: Any) -> str:
    if not isinstance(value, str):
        raise Unbuildable("a text field holds something else")
    return value


def _object(value: Any) -> dict:
    if not isinstance(value, dict):
        raise Unbuildable("a message field holds something else")
    return value


def _list(value: Any) -> list:
    if not isinstance(value, list):
        raise Unbuildable("an array field holds something else")
    return value


def _base64(value: Any) -> bytes:
    try:
        return base64.b64decode(_text(value), validate=True)
    except (binascii.Error, ValueError):
        raise Unbuildable("bytes that are not base64") from None


# The types written as CDR here, without rosbags' message objects.
_ENCODERS = {"nav_msgs/msg/Odometry": _odometry_cdr}
_BUILDERS = {
    "sensor_msgs/msg/Imu": _imu,
    "sensor_msgs/msg/Image": _image,
    "sensor_msgs/msg/CompressedImage": _compressed_image,
}
