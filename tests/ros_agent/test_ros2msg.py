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
from tests.support.custom_msgs import (
    INSPECTION,
    LEARNED,
    MSG_DIR,
    inspection,
    inspection_record,
)
from tests.support.recordings import TOPICS, make_samples, ros1_store, ros2_store


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


# --- custom types, learned from .msg files --------------------------------------------------


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_a_custom_nested_type_is_learned_from_its_msg_files_and_read_like_any(distro):
    typestore = ros2msg.default_typestore(distro)
    inspection_type = ros2_name(INSPECTION)
    assert inspection_type not in typestore.fielddefs
    learned = ros2msg.learn_message_types(typestore, [inspection_type], [MSG_DIR])
    assert learned == LEARNED  # and the Header, Point and Time the distribution has already
    assert ros2msg.learn_message_types(typestore, [inspection_type], [MSG_DIR]) == []
    sent = inspection(typestore, 3)
    # The CDR a ROS 2 publisher sends, read back: every field, through the generic walk.
    received = typestore.deserialize_cdr(
        typestore.serialize_cdr(sent, inspection_type), inspection_type
    )
    assert message_data(received, INSPECTION) == inspection_record(3)
    assert received.MODE_AUTO == 1


def test_the_distribution_chooses_the_type_store():
    humble = ros2msg.default_typestore("humble").fielddefs
    jazzy = ros2msg.default_typestore("jazzy").fielddefs
    # Jazzy added type descriptions (type_description_interfaces) that Humble has not.
    added = set(jazzy) - set(humble)
    assert added
    assert all(name not in humble for name in added)


def test_a_type_found_in_no_folder_is_refused_naming_where_it_looked(tmp_path):
    typestore = ros2msg.default_typestore()
    with pytest.raises(
        ros2msg.MessageTypeUnknown, match=rf"no my_pkg/msg/Secret\.msg in {tmp_path}"
    ):
        ros2msg.learn_message_types(typestore, ["my_pkg/msg/Secret"], [tmp_path])
    # A definition naming a type that is nowhere: nothing is registered.
    folder = tmp_path / "my_pkg" / "msg"
    folder.mkdir(parents=True)
    (folder / "Secret.msg").write_text("Missing inner\nint32 x\n")
    with pytest.raises(ros2msg.MessageTypeUnknown, match=r"no my_pkg/msg/Missing\.msg"):
        ros2msg.learn_message_types(typestore, ["my_pkg/msg/Secret"], [tmp_path])
    assert "my_pkg/msg/Secret" not in typestore.fielddefs
    (folder / "Secret.msg").write_text("int32[ x\n")
    with pytest.raises(ros2msg.MessageTypeUnknown, match="cannot read the definition of"):
        ros2msg.learn_message_types(typestore, ["my_pkg/msg/Secret"], [tmp_path])


def test_a_package_folder_itself_may_be_named(tmp_path):
    typestore = ros2msg.default_typestore()
    package = MSG_DIR / "authros_test_msgs"
    assert ros2msg.learn_message_types(typestore, [ros2_name(INSPECTION)], [package]) == LEARNED
