"""ROS 2 messages (as rosbags decodes them) seen as the ROS 1 messages the extractors read.

rosbags decodes CDR (a DDS sample, a .db3 or .mcap record) and ROS 1 bag records into its
type store's classes: `nav_msgs/msg/Odometry`, stamps as `builtin_interfaces/msg/Time` (`sec`,
`nanosec`), arrays as numpy arrays. `ros1_view` wraps such a message so that the extractors of
ros_agent.extractors read it unchanged (`header.seq`, `stamp.secs`/`nsecs`), so a ROS 2 or
recorded message becomes the very record a rospy message of the same type becomes; any other
type is walked field by field (`as_record`) with the generic walk's conventions.
"""

import base64
import dataclasses
import math
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from ros_agent.extractors import JsonDict, extract, header, iso_utc, stamp_datetime

_TIME_TYPES = ("builtin_interfaces/msg/Time", "std_msgs/msg/Time")
_DURATION_TYPES = ("builtin_interfaces/msg/Duration", "std_msgs/msg/Duration")
_HEADER_TYPE = "std_msgs/msg/Header"


def default_typestore() -> Typestore:
    """rosbags' type store of ROS 2 Humble: the common interfaces, with the CDR codecs."""
    return get_typestore(Stores.ROS2_HUMBLE)


def ros1_name(ros2_type: str) -> str:
    """`nav_msgs/msg/Odometry` -> `nav_msgs/Odometry`, the name configs and envelopes use."""
    package, _, name = ros2_type.rpartition("/")
    return f"{package.split('/', 1)[0]}/{name}"


def ros2_name(ros_type: str) -> str:
    """`nav_msgs/Odometry` -> `nav_msgs/msg/Odometry`, the name rosbags and DDS use."""
    if ros_type.count("/") >= 2:
        return ros_type
    package, name = ros_type.split("/", 1)
    return f"{package}/msg/{name}"


def message_data(msg: Any, ros_type: str) -> JsonDict:
    """The record data `K` of a rosbags message whose config type is `ros_type`."""
    return extract(ros1_view(msg), ros_type)


def ros1_view(value: Any) -> Any:
    """A rosbags message as the extractors read a rospy one; other values unchanged."""
    if not dataclasses.is_dataclass(value) or isinstance(value, type):
        return value
    msgtype = getattr(value, "__msgtype__", "")
    if msgtype in _TIME_TYPES or msgtype in _DURATION_TYPES:
        return _StampView(value)
    return _MessageView(value)


class _StampView:
    """A ROS 2 Time or Duration with the ROS 1 names `secs` and `nsecs`."""

    def __init__(self, stamp: Any) -> None:
        self.secs = int(stamp.sec)
        self.nsecs = int(stamp.nanosec)


class _MessageView:
    """Attribute access to a rosbags message, nested messages and stamps wrapped in turn.

    A ROS 2 Header has no `seq`: it reads as 0, so headers keep the ROS 1 record's shape.
    """

    def __init__(self, msg: Any) -> None:
        self._msg = msg

    def __getattr__(self, name: str) -> Any:
        try:
            value = getattr(self._msg, name)
        except AttributeError:
            if name == "seq" and self._msg.__msgtype__ == _HEADER_TYPE:
                return 0
            raise
        return ros1_view(value)

    def as_record(self) -> JsonDict:
        """The generic field-by-field record (extractors.message_to_dict for ROS 1)."""
        return _message_dict(self._msg)


def message_fields(msg: Any) -> list[str]:
    """The names of a rosbags message's fields, in order, without its constants."""
    # rosbags declares constants and __msgtype__ as ClassVar (as strings, so dataclasses
    # lists them as fields).
    return [
        field.name
        for field in dataclasses.fields(msg)
        if not str(field.type).startswith("ClassVar")
    ]


def _message_dict(msg: Any) -> JsonDict:
    if msg.__msgtype__ == _HEADER_TYPE:
        return header(ros1_view(msg))
    return {name: _field(getattr(msg, name)) for name in message_fields(msg)}


def _field(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        msgtype = getattr(value, "__msgtype__", "")
        if msgtype in _TIME_TYPES:
            return _time(value)
        if msgtype in _DURATION_TYPES:
            return {"secs": int(value.sec), "nsecs": int(value.nanosec)}
        return _message_dict(value)
    if isinstance(value, np.ndarray):
        if value.dtype == np.uint8:
            return _b64(value.tobytes())
        return [_field(item) for item in value.tolist()]
    if isinstance(value, bytes | bytearray):
        return _b64(bytes(value))
    if isinstance(value, list | tuple):
        return [_field(item) for item in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value


def _time(stamp: Any) -> JsonDict:
    view = _StampView(stamp)
    return {"secs": view.secs, "nsecs": view.nsecs, "iso": iso_utc(stamp_datetime(view))}


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")
