"""ROS 2 messages (as rosbags decodes them) seen as the ROS 1 messages the extractors read.

rosbags decodes CDR (a DDS sample, a .db3 or .mcap record) and ROS 1 bag records into its
type store's classes: `nav_msgs/msg/Odometry`, stamps as `builtin_interfaces/msg/Time` (`sec`,
`nanosec`), arrays as numpy arrays. `ros1_view` wraps such a message so that the extractors of
ros_agent.extractors read it unchanged (`header.seq`, `stamp.secs`/`nsecs`), so a ROS 2 or
recorded message becomes the very record a rospy message of the same type becomes; any other
type is walked field by field (`as_record`) with the generic walk's conventions.

The type store is ROS 2 Humble's or Jazzy's (`ros2_distro` in agent.yaml). A type it does not
hold, a robot's custom message, is learned from its `.msg` definition (`learn_message_types`):
`<folder>/<package>/msg/<Name>.msg` in the folders agent.yaml's `msg_dirs` names, then in the
robot's installed share folders (AgentConfig.msg_search_dirs), with every type its fields
name in turn, through rosbags' own parser and registration; from there it is read like any
other type (DDS, CDR, the generic walk).
"""

import base64
import dataclasses
import math
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

from ros_agent.config import DEFAULT_ROS2_DISTRO
from ros_agent.extractors import JsonDict, extract, header, iso_utc, stamp_datetime

_TIME_TYPES = ("builtin_interfaces/msg/Time", "std_msgs/msg/Time")
_DURATION_TYPES = ("builtin_interfaces/msg/Duration", "std_msgs/msg/Duration")
_HEADER_TYPE = "std_msgs/msg/Header"


class MessageTypeUnknown(ValueError):
    """A message type is neither in the type store nor defined by a readable `.msg` file."""


def default_typestore(distro: str = DEFAULT_ROS2_DISTRO) -> Typestore:
    """rosbags' type store of a ROS 2 distribution (`humble`, `jazzy`): the common interfaces,
    with the CDR codecs."""
    return get_typestore(Stores(f"ros2_{distro}"))


def learn_message_types(
    typestore: Typestore, ros2_types: Iterable[str], msg_dirs: Sequence[Path]
) -> list[str]:
    """Register in `typestore` each of `ros2_types` it does not know, and every type their
    fields name that it does not know either, from `.msg` files in `msg_dirs`: the names
    learned (none when it knew them all)."""
    learned: dict[str, Any] = {}
    pending = list(ros2_types)
    while pending:
        name = pending.pop()
        if name in typestore.fielddefs or name in learned:
            continue
        path = _definition_file(name, msg_dirs)
        try:
            types = get_types_from_msg(path.read_text(encoding="utf-8"), name)
        except (OSError, UnicodeDecodeError, TypesysError) as exc:
            raise MessageTypeUnknown(
                f"cannot read the definition of {name} in {path}: {exc}"
            ) from None
        learned.update(types)
        pending.extend(
            named for _, fields in types.values() for _, desc in fields for named in _names(desc)
        )
    if learned:
        typestore.register(learned)
    return sorted(learned)


def _definition_file(ros2_type: str, msg_dirs: Sequence[Path]) -> Path:
    parts = ros2_type.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not parts[0] or not parts[2]:
        raise MessageTypeUnknown(f"unknown message type {ros2_type}")
    package, _, name = parts
    for folder in msg_dirs:
        for candidate in (folder / package / "msg" / f"{name}.msg", folder / "msg" / f"{name}.msg"):
            if candidate.parent.parent.name == package and candidate.is_file():
                return candidate
    where = ", ".join(str(folder) for folder in msg_dirs) or "no folder (set msg_dirs)"
    raise MessageTypeUnknown(
        f"unknown message type {ros2_type}: no {package}/msg/{name}.msg in {where}"
    )


def _names(desc: tuple[Any, Any]) -> Iterator[str]:
    """The message types a rosbags field description names, at any depth of arrays."""
    node, detail = desc
    if node == Nodetype.NAME:
        yield detail
    elif node in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        yield from _names(detail[0])


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
