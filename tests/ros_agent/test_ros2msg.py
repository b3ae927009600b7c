"""A message decoded by rosbags (ROS 2 CDR, or a recorded ROS 1 bag) becomes the very record
the ROS 1 extractors make of the same rospy message: the portal's viewers read both alike."""

import json

import genpy
import numpy as np
import pytest
import roslib.message

from ros_agent import ros2msg
from ros_agent.extractors import extract
from ros_agent.ros2msg import message_data, ros1_name, ros2_name
from tests.ros_agent.recordings import TOPICS, make_samples, ros1_store, ros2_store


def _as_genpy(msg, slot_type: str | None = None):
    """The rospy (genpy) message with the values of a rosbags message of the ROS 1 store."""
    msgtype = msg.__msgtype__
    if msgtype == "builtin_interfaces/msg/Time":
        return genpy.Time(msg.sec, msg.nanosec)
    cls = roslib.message.get_message_class(ros1_name(msgtype))
    out = cls()
    for name, slot in zip(cls.__slots__, cls._slot_types, strict=True):
        value = getattr(msg, name)
        if hasattr(value, "__msgtype__"):
            value = _as_genpy(value, slot)
        elif isinstance(value, np.ndarray):
            value = value.tobytes() if slot in ("uint8[]", "char[]") else value.tolist()
        elif isinstance(value, list):
            value = [_as_genpy(item) for item in value]
        setattr(out, name, value)
    return out


@pytest.mark.parametrize(("topic", "ros_type"), TOPICS)
def test_a_recorded_ros1_message_gives_the_rospy_record(topic, ros_type):
    ts = ros1_store()
    for sample in [s for s in make_samples(ts, 2) if s.topic == topic]:
        rospy_record = extract(_as_genpy(sample.msg), ros_type)
        assert message_data(sample.msg, ros_type) == rospy_record
        json.dumps(rospy_record, allow_nan=False)


@pytest.mark.parametrize(("topic", "ros_type"), TOPICS)
def test_a_ros2_message_gives_the_rospy_record_with_header_seq_0(topic, ros_type):
    ros1, ros2 = ros1_store(), ros2_store()
    pairs = zip(make_samples(ros1, 2), make_samples(ros2, 2), strict=True)
    for old, new in [(a, b) for a, b in pairs if a.topic == topic]:
        rospy_msg = _as_genpy(old.msg)
        if hasattr(rospy_msg, "header"):
            rospy_msg.header.seq = 0  # ROS 2 headers have no seq
        assert message_data(new.msg, ros_type) == extract(rospy_msg, ros_type)


def test_names_and_a_type_only_the_generic_walk_knows():
    assert ros2_name("nav_msgs/Odometry") == "nav_msgs/msg/Odometry"
    assert ros2_name("nav_msgs/msg/Odometry") == "nav_msgs/msg/Odometry"
    assert ros1_name("nav_msgs/msg/Odometry") == "nav_msgs/Odometry"
    ts = ros2_store()
    t = ts.types
    status = t["diagnostic_msgs/msg/DiagnosticStatus"](
        level=b"\x02",
        name="motor",
        message="hot",
        hardware_id="m1",
        values=[t["diagnostic_msgs/msg/KeyValue"](key="temp", value="91")],
    )
    data = ros2msg.message_data(status, "diagnostic_msgs/DiagnosticStatus")
    assert data["name"] == "motor"
    assert data["values"] == [{"key": "temp", "value": "91"}]
    assert "OK" not in data  # constants are not fields
    duration = t["builtin_interfaces/msg/Duration"](sec=3, nanosec=5)
    goal = t["std_msgs/msg/Float64MultiArray"](
        layout=t["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
        data=np.array([1.5, float("nan")]),
    )
    assert ros2msg.message_data(goal, "std_msgs/Float64MultiArray")["data"] == [1.5, None]
    assert ros2msg._field(duration) == {"secs": 3, "nsecs": 5}
