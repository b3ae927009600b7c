"""ROS 2 topics over Cyclone DDS without a ROS 2 installation.

ROS 2 (rmw_cyclonedds) maps topic `/x` to the DDS topic `rt/x` whose type is
`pkg::msg::dds_::Type_`, and sends CDR that rosbags' type store reads. `idl_type` builds the
matching Cyclone DDS IDL struct from a rosbags type definition, field by field, so Cyclone's
discovery matches ROS 2 peers by name and layout; readers hand the raw CDR (`RawSample`) to
rosbags, so the decoding is the same one that reads recorded bags.

`write_loopback_config` writes the CYCLONEDDS_URI the project uses in tests and `make run`:
loopback interface only, multicast off, peer 127.0.0.1, so no DDS traffic leaves the machine.
"""

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from ros_agent.ros2msg import message_fields

CYCLONEDDS_URI = "CYCLONEDDS_URI"
# Types usually published with ROS 2's sensor-data QoS (best effort): a best-effort reader
# matches best-effort and reliable publishers alike. Other topics are read reliably, which
# matches ROS 2's default (reliable) publishers.
SENSOR_TYPES = frozenset(
    {
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/CompressedImage",
        "sensor_msgs/msg/Imu",
        "sensor_msgs/msg/PointCloud2",
        "sensor_msgs/msg/LaserScan",
    }
)
HISTORY_DEPTH = 100

_LOOPBACK_XML = """<?xml version="1.0" encoding="UTF-8"?>
<!-- Written by ros_agent.dds: DDS on this machine only (loopback, no multicast). -->
<CycloneDDS xmlns="https://cdds.io/config">
  <Domain Id="any">
    <General>
      <Interfaces>
        <NetworkInterface address="127.0.0.1"/>
      </Interfaces>
      <AllowMulticast>false</AllowMulticast>
    </General>
    <Discovery>
      <ParticipantIndex>auto</ParticipantIndex>
      <MaxAutoParticipantIndex>{max_participants}</MaxAutoParticipantIndex>
      <Peers>
        <Peer address="127.0.0.1"/>
      </Peers>
    </Discovery>
  </Domain>
</CycloneDDS>
"""


class DdsError(RuntimeError):
    """A ROS 2 type cannot be mapped to DDS, or Cyclone DDS cannot start."""


def write_loopback_config(path: Path, *, max_participants: int = 20) -> Path:
    """Write a Cyclone DDS config for this machine only; returns the path (for CYCLONEDDS_URI)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(_LOOPBACK_XML.format(max_participants=max_participants), encoding="utf-8")
    return path


def loopback_environment(path: Path, *, domain_id: int | None = None) -> dict[str, str]:
    """Environment variables that put a process on the loopback config (and a domain)."""
    env = {CYCLONEDDS_URI: Path(path).resolve().as_uri()}
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    return env


def domain_id_from_environment() -> int:
    """ROS_DOMAIN_ID as ROS 2 reads it (0 when unset)."""
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    if not value:
        return 0
    if not value.isdigit() or int(value) > 232:
        raise DdsError(f"ROS_DOMAIN_ID must be a number from 0 to 232, got {value!r}")
    return int(value)


def dds_topic_name(topic: str) -> str:
    """ROS 2 topic `/robot/odom` -> DDS topic `rt/robot/odom`."""
    return "rt/" + topic.lstrip("/")


def dds_type_name(ros2_type: str) -> str:
    """`nav_msgs/msg/Odometry` -> `nav_msgs::msg::dds_::Odometry_`."""
    *namespace, name = ros2_type.split("/")
    return "::".join([*namespace, "dds_", f"{name}_"])


@dataclass
class RawSample:
    """A DDS sample as CDR bytes (with their 4-byte encapsulation header), for rosbags."""

    cdr: bytes
    sample_info: Any = None


def idl_type(typestore: Typestore, ros2_type: str, *, raw: bool = False) -> type:
    """The Cyclone DDS struct of a ROS 2 type; with raw=True readers give `RawSample`s."""
    from cyclonedds.idl import IdlStruct, make_idl_struct

    cache: dict[str, type] = {}
    struct = _struct(typestore, ros2_type, cache)
    if not raw:
        return struct

    def deserialize(cls: type, data: bytes, **_: Any) -> RawSample:
        return RawSample(bytes(data))

    # The same name and members (so discovery matches), but the CDR is left to rosbags.
    fields = dict(struct.__annotations__)
    raw_type = make_idl_struct(struct.__name__, dds_type_name(ros2_type), fields, bases=())
    assert issubclass(raw_type, IdlStruct)
    raw_type.deserialize = classmethod(deserialize)
    return raw_type


def _struct(typestore: Typestore, ros2_type: str, cache: dict[str, type]) -> type:
    from cyclonedds.idl import make_idl_struct

    if ros2_type in cache:
        return cache[ros2_type]
    try:
        _, fields = typestore.fielddefs[ros2_type]
    except KeyError:
        raise DdsError(f"unknown message type {ros2_type}") from None
    members = {name: _member(typestore, desc, cache) for name, desc in fields}
    if not members:  # an empty ROS 2 message has one uint8 member on the wire
        from cyclonedds.idl import types

        members = {"structure_needs_at_least_one_member": types.uint8}
    cls = make_idl_struct(ros2_type.replace("/", "__"), dds_type_name(ros2_type), members)
    cache[ros2_type] = cls
    return cls


def _member(typestore: Typestore, desc: tuple[Any, Any], cache: dict[str, type]) -> Any:
    from cyclonedds.idl import types
    from rosbags.typesys.base import Nodetype

    node, detail = desc
    if node == Nodetype.BASE:
        name, bound = detail
        return _base(name, bound)
    if node == Nodetype.NAME:
        return _struct(typestore, detail, cache)
    if node == Nodetype.ARRAY:
        element, length = detail
        return types.array[_member(typestore, element, cache), length]
    if node == Nodetype.SEQUENCE:
        element, bound = detail
        inner = _member(typestore, element, cache)
        return types.sequence[inner, bound] if bound else types.sequence[inner]
    raise DdsError(f"cannot map the field {desc!r} to DDS")


def _base(name: str, bound: int) -> Any:
    from cyclonedds.idl import types

    if name == "string":
        return types.bounded_str[bound] if bound else str
    simple: Mapping[str, Any] = {
        "bool": bool,
        "byte": types.uint8,
        "char": types.uint8,
        "int8": types.int8,
        "uint8": types.uint8,
        "int16": types.int16,
        "uint16": types.uint16,
        "int32": types.int32,
        "uint32": types.uint32,
        "int64": types.int64,
        "uint64": types.uint64,
        "float32": types.float32,
        "float64": types.float64,
    }
    if name not in simple:
        raise DdsError(f"the field type {name} has no DDS mapping here")
    return simple[name]


def reader_qos(ros2_type: str, best_effort: bool | None = None) -> Any:
    """QoS of a reader of `ros2_type` that matches ROS 2 publishers of it: best effort for
    SENSOR_TYPES (or when `best_effort`), else reliable; volatile (matches transient-local
    publishers too)."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    if best_effort is None:
        best_effort = ros2_type in SENSOR_TYPES
    reliability = (
        Policy.Reliability.BestEffort
        if best_effort
        else Policy.Reliability.Reliable(duration(seconds=1))
    )
    return Qos(
        reliability,
        Policy.Durability.Volatile,
        Policy.History.KeepLast(HISTORY_DEPTH),
    )


def writer_qos(*, best_effort: bool = False) -> Any:
    """ROS 2's default publisher QoS (reliable, volatile, keep last 10), or its sensor-data
    reliability (best effort)."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.util import duration

    return Qos(
        Policy.Reliability.BestEffort
        if best_effort
        else Policy.Reliability.Reliable(duration(seconds=1)),
        Policy.Durability.Volatile,
        Policy.History.KeepLast(10),
    )


def idl_sample(struct: type, msg: Any) -> Any:
    """A rosbags message as an instance of its Cyclone DDS struct (from `idl_type`), to write."""
    hints = struct.__annotations__
    values = {}
    for name in message_fields(msg):
        value = getattr(msg, name)
        if dataclasses.is_dataclass(value):
            value = idl_sample(hints[name], value)
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, list) and value and dataclasses.is_dataclass(value[0]):
            element = hints[name].__metadata__[0].subtype
            value = [idl_sample(element, item) for item in value]
        values[name] = value
    return struct(**values)
