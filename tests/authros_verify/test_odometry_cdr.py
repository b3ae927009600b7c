"""An odometry record's CDR, written directly by authros_verify.messages, is byte for byte what
rosbags serialises from the message built field by field (the MCAP files exported before, and
any other tool, make the same bytes), and a record that does not fit the type still goes on a
JSON channel."""

import json
import math
import random

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from authros_verify.messages import message_encode

pytestmark = pytest.mark.nodb

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
TYPES = TYPESTORE.types


def _odometry(rng: random.Random, frame: str, child: str) -> dict:
    """The extractor's shape of nav_msgs/Odometry (ros_agent/extractors.py), numbers random:
    floats, whole numbers, null (NaN), negative zero."""

    def number() -> float | int | None:
        return rng.choice(
            [rng.uniform(-1e6, 1e6), rng.randint(-(10**12), 10**12), None, -0.0, 1e300]
        )

    def vector(names: str) -> dict:
        return {name: number() for name in names}

    return {
        "header": {
            "seq": rng.randint(0, 10**6),
            "stamp": {"secs": rng.randint(-(2**31), 2**31 - 1), "nsecs": rng.randint(0, 10**9 - 1)},
            "frame_id": frame,
        },
        "child_frame_id": child,
        "position": vector("xyz"),
        "orientation": vector("xyzw"),
        "linear_velocity": vector("xyz"),
        "angular_velocity": vector("xyz"),
        "pose_covariance": [number() for _ in range(36)],
        "twist_covariance": [number() for _ in range(36)],
    }


def _float(value: float | int | None) -> float:
    return math.nan if value is None else float(value)


def _rosbags_cdr(data: dict) -> bytes:
    """The message built from rosbags' own types and serialised by rosbags."""

    def vector(kind: str, value: dict, names: str) -> object:
        return TYPES[kind](**{name: _float(value[name]) for name in names})

    stamp = data["header"]["stamp"]
    header = TYPES["std_msgs/msg/Header"](
        stamp=TYPES["builtin_interfaces/msg/Time"](sec=stamp["secs"], nanosec=stamp["nsecs"]),
        frame_id=data["header"]["frame_id"],
    )
    pose = TYPES["geometry_msgs/msg/Pose"](
        position=vector("geometry_msgs/msg/Point", data["position"], "xyz"),
        orientation=vector("geometry_msgs/msg/Quaternion", data["orientation"], "xyzw"),
    )
    twist = TYPES["geometry_msgs/msg/Twist"](
        linear=vector("geometry_msgs/msg/Vector3", data["linear_velocity"], "xyz"),
        angular=vector("geometry_msgs/msg/Vector3", data["angular_velocity"], "xyz"),
    )
    covariance = [
        [_float(v) for v in data[name]] for name in ("pose_covariance", "twist_covariance")
    ]
    message = TYPES["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id=data["child_frame_id"],
        pose=TYPES["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose, covariance=np.array(covariance[0], dtype=np.float64)
        ),
        twist=TYPES["geometry_msgs/msg/TwistWithCovariance"](
            twist=twist, covariance=np.array(covariance[1], dtype=np.float64)
        ),
    )
    return bytes(TYPESTORE.serialize_cdr(message, "nav_msgs/msg/Odometry"))


def _plaintext(data: dict) -> bytes:
    record = {"K": data, "Owner": "alice", "Time": "2026-05-01T12:00:00Z"}
    return json.dumps({**record, "Type": "nav_msgs/Odometry"}).encode()


# Frame ids of every length modulo 4 and 8 (the alignment of what follows), and not ASCII.
FRAMES = ["", "o", "od", "odo", "odom", "odom_", "base_link", "ködöm", "機器人/odom"]


@pytest.mark.parametrize("frame", FRAMES)
def test_odometry_cdr_is_rosbags_byte_for_byte(frame):
    rng = random.Random(frame)
    for child in FRAMES:
        data = _odometry(rng, frame, child)
        encoded = message_encode(data_type="nav_msgs/Odometry", plaintext=_plaintext(data))
        assert encoded.message_encoding == "cdr"
        assert encoded.schema_name == "nav_msgs/msg/Odometry"
        assert encoded.data == _rosbags_cdr(data)
        stamp = data["header"]["stamp"]
        if stamp["secs"] >= 0:
            assert encoded.stamp_ns == stamp["secs"] * 10**9 + stamp["nsecs"]


@pytest.mark.parametrize(
    "spoil",
    [
        lambda data: data["pose_covariance"].pop(),
        lambda data: data["twist_covariance"].append(0.0),
        lambda data: data["pose_covariance"].__setitem__(3, True),
        lambda data: data["position"].__setitem__("x", "1.0"),
        lambda data: data["orientation"].__setitem__("w", [1.0]),
        lambda data: data["header"]["stamp"].__setitem__("nsecs", 10**9),
        lambda data: data["header"]["stamp"].__setitem__("secs", 2**31),
        lambda data: data["header"]["stamp"].__setitem__("secs", 1.5),
        lambda data: data.__setitem__("child_frame_id", 7),
        lambda data: data["header"].__setitem__("frame_id", "\ud800"),
        lambda data: data.__setitem__("linear_velocity", [0.0, 0.0, 0.0]),
    ],
)
def test_an_odometry_that_does_not_fit_its_type_goes_on_a_json_channel(spoil):
    data = _odometry(random.Random(1), "odom", "base_link")
    spoil(data)
    plaintext = _plaintext(data)
    encoded = message_encode(data_type="nav_msgs/Odometry", plaintext=plaintext)
    assert (encoded.message_encoding, encoded.data) == ("json", plaintext)
