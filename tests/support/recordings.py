"""Messages of the types the agent knows, with known values, and recordings of them written
with rosbags' writers (ROS 1 .bag, ROS 2 .db3 and .mcap), for the ROS 2 and import tests.

`expected_data` says, independently of the agent's converters, what record data `K` each
message must become: the values that were published or recorded.
"""

import base64
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

ODOM = ("/robot/odom", "nav_msgs/Odometry")
IMAGE = ("/camera/image", "sensor_msgs/Image")
DEPTH = ("/camera/depth", "sensor_msgs/Image")
COMPRESSED = ("/camera/compressed", "sensor_msgs/CompressedImage")
IMU = ("/imu", "sensor_msgs/Imu")
POINTS = ("/points", "sensor_msgs/PointCloud2")
POSES = ("/poses", "geometry_msgs/PoseArray")
CHATTER = ("/chatter", "std_msgs/String")
TOPICS = (ODOM, IMAGE, DEPTH, COMPRESSED, IMU, POINTS, POSES, CHATTER)
BASE_NS = 1_700_000_000_123_456_789


def ros1_store() -> Typestore:
    return get_typestore(Stores.ROS1_NOETIC)


def ros2_store() -> Typestore:
    return get_typestore(Stores.ROS2_HUMBLE)


def ros2_type(ros_type: str) -> str:
    package, name = ros_type.split("/")
    return f"{package}/msg/{name}"


@dataclass(frozen=True)
class Sample:
    topic: str
    ros_type: str  # as the config names it: nav_msgs/Odometry
    msg: Any
    stamp_ns: int  # the header stamp, or the recording time where there is no header
    index: int  # which message of its topic
    has_header: bool = True


def _stamp(ts: Typestore, ns: int) -> Any:
    return ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ts: Typestore, ns: int, frame: str, seq: int) -> Any:
    cls = ts.types["std_msgs/msg/Header"]
    if "seq" in cls.__dataclass_fields__:
        return cls(seq=seq, stamp=_stamp(ts, ns), frame_id=frame)
    return cls(stamp=_stamp(ts, ns), frame_id=frame)


def _vector(ts: Typestore, x: float, y: float, z: float) -> Any:
    return ts.types["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)


def _quaternion(ts: Typestore, i: int) -> Any:
    return ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.1 * i, w=1.0 - 0.01 * i)


def _pose(ts: Typestore, i: int) -> Any:
    point = ts.types["geometry_msgs/msg/Point"](x=1.5 + i, y=-2.25 * i, z=0.125)
    return ts.types["geometry_msgs/msg/Pose"](position=point, orientation=_quaternion(ts, i))


def rgb_pixels(i: int) -> np.ndarray:
    """5x3 rgb8, every channel a different value."""
    return ((np.arange(3 * 5 * 3, dtype=np.uint16).reshape(3, 5, 3) * 5 + i) % 256).astype(np.uint8)


def depth_pixels(i: int) -> np.ndarray:
    return (np.arange(4 * 6, dtype=np.uint32).reshape(4, 6) * 1000 + i).astype(np.uint16)


def jpeg_bytes(i: int) -> bytes:
    ok, data = cv2.imencode(".jpg", np.full((8, 8, 3), (20 * i) % 256, np.uint8))
    assert ok
    return data.tobytes()


def points_bytes(i: int) -> bytes:
    return np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0 + i]], dtype="<f4").tobytes()


def make_samples(ts: Typestore, count: int, *, base_ns: int = BASE_NS) -> list[Sample]:
    """`count` messages of each topic in TOPICS, 10 ms apart, values depending on the index."""
    t = ts.types
    samples: list[Sample] = []
    for i in range(count):
        ns = base_ns + i * 10_000_000

        def header(frame: str, i: int = i, ns: int = ns) -> Any:
            return _header(ts, ns, frame, seq=100 + i)

        covariance = np.arange(36, dtype=np.float64) * (i + 1)
        odom = t["nav_msgs/msg/Odometry"](
            header=header("odom"),
            child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=_pose(ts, i), covariance=covariance
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=_vector(ts, 0.5 + i, 0.0, 0.0), angular=_vector(ts, 0.0, 0.0, -0.25)
                ),
                covariance=np.zeros(36),
            ),
        )
        rgb = rgb_pixels(i)
        padded = np.zeros((3, 16), np.uint8)  # step 16 > 5 * 3: rows are padded
        padded[:, :15] = rgb.reshape(3, 15)
        image = t["sensor_msgs/msg/Image"](
            header=header("camera"),
            height=3,
            width=5,
            encoding="rgb8",
            is_bigendian=0,
            step=16,
            data=padded.reshape(-1),
        )
        depth = depth_pixels(i)
        depth_msg = t["sensor_msgs/msg/Image"](
            header=header("depth"),
            height=4,
            width=6,
            encoding="16UC1",
            is_bigendian=0,
            step=12,
            data=np.frombuffer(depth.astype("<u2").tobytes(), np.uint8),
        )
        compressed = t["sensor_msgs/msg/CompressedImage"](
            header=header("camera"), format="jpeg", data=np.frombuffer(jpeg_bytes(i), np.uint8)
        )
        imu = t["sensor_msgs/msg/Imu"](
            header=header("imu"),
            orientation=_quaternion(ts, i),
            orientation_covariance=np.full(9, 0.5),
            angular_velocity=_vector(ts, 0.01 * i, 0.02, 0.03),
            angular_velocity_covariance=np.arange(9, dtype=np.float64),
            linear_acceleration=_vector(ts, 0.0, 0.0, 9.81),
            linear_acceleration_covariance=np.zeros(9),
        )
        field = t["sensor_msgs/msg/PointField"]
        points = t["sensor_msgs/msg/PointCloud2"](
            header=header("lidar"),
            height=1,
            width=2,
            fields=[
                field(name=name, offset=4 * k, datatype=7, count=1) for k, name in enumerate("xyz")
            ],
            is_bigendian=False,
            point_step=12,
            row_step=24,
            data=np.frombuffer(points_bytes(i), np.uint8),
            is_dense=True,
        )
        poses = t["geometry_msgs/msg/PoseArray"](
            header=header("map"), poses=[_pose(ts, i), _pose(ts, i + 1)]
        )
        chatter = t["std_msgs/msg/String"](data=f"hello {i} \u00e9")
        for (topic, ros_type), msg in zip(
            TOPICS, (odom, image, depth_msg, compressed, imu, points, poses, chatter), strict=True
        ):
            samples.append(
                Sample(topic, ros_type, msg, ns, i, has_header=(topic, ros_type) != CHATTER)
            )
    return samples


# --- what each must become ----------------------------------------------------------------------


def _time(ns: int) -> dict:
    return {"secs": ns // 10**9, "nsecs": ns % 10**9}


def _header_dict(header: Any, seq: int) -> dict:
    return {
        "seq": seq,
        "stamp": _time(header.stamp.sec * 10**9 + header.stamp.nanosec),
        "frame_id": header.frame_id,
    }


def _xyz(value: Any) -> dict:
    return {"x": value.x, "y": value.y, "z": value.z}


def _xyzw(value: Any) -> dict:
    return {**_xyz(value), "w": value.w}


def expected_data(sample: Sample, *, ros1: bool) -> dict:
    """The record data `K` of a sample (stamps without their `iso`, images decoded: see
    `comparable`)."""
    msg = sample.msg
    seq = 100 + sample.index if ros1 else 0
    topic_type = (sample.topic, sample.ros_type)
    if topic_type == CHATTER:
        return {"data": msg.data}
    head = _header_dict(msg.header, seq)
    if topic_type == ODOM:
        return {
            "header": head,
            "child_frame_id": msg.child_frame_id,
            "position": _xyz(msg.pose.pose.position),
            "orientation": _xyzw(msg.pose.pose.orientation),
            "linear_velocity": _xyz(msg.twist.twist.linear),
            "angular_velocity": _xyz(msg.twist.twist.angular),
            "pose_covariance": [float(v) for v in msg.pose.covariance],
            "twist_covariance": [float(v) for v in msg.twist.covariance],
        }
    if topic_type == IMAGE:
        return {
            "header": head,
            "width": 5,
            "height": 3,
            "encoding": "rgb8",
            "format": "png",
            "pixels": rgb_pixels(sample.index)[..., ::-1].tolist(),
        }  # PNG decodes as BGR
    if topic_type == DEPTH:
        return {
            "header": head,
            "width": 6,
            "height": 4,
            "encoding": "16UC1",
            "format": "png",
            "pixels": depth_pixels(sample.index).tolist(),
        }
    if topic_type == COMPRESSED:
        return {
            "header": head,
            "format": "jpeg",
            "data": base64.b64encode(jpeg_bytes(sample.index)).decode(),
        }
    if topic_type == IMU:
        return {
            "header": head,
            "orientation": _xyzw(msg.orientation),
            "orientation_covariance": [float(v) for v in msg.orientation_covariance],
            "angular_velocity": _xyz(msg.angular_velocity),
            "angular_velocity_covariance": [float(v) for v in msg.angular_velocity_covariance],
            "linear_acceleration": _xyz(msg.linear_acceleration),
            "linear_acceleration_covariance": [
                float(v) for v in msg.linear_acceleration_covariance
            ],
        }
    if topic_type == POINTS:
        return {
            "header": head,
            "height": 1,
            "width": 2,
            "fields": [
                {"name": name, "offset": 4 * k, "datatype": 7, "count": 1}
                for k, name in enumerate("xyz")
            ],
            "is_bigendian": False,
            "point_step": 12,
            "row_step": 24,
            "data": base64.b64encode(points_bytes(sample.index)).decode(),
            "is_dense": True,
        }
    if topic_type == POSES:
        return {
            "header": head,
            "poses": [
                {"position": _xyz(p.position), "orientation": _xyzw(p.orientation)}
                for p in msg.poses
            ],
        }
    raise AssertionError(f"no expectation for {topic_type}")


def comparable(data: dict) -> dict:
    """Record data with stamps' `iso` dropped (checked apart) and PNG images decoded."""
    data = _without_iso(data)
    if data.get("format") == "png":
        png = base64.b64decode(data.pop("data"))
        data["pixels"] = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED).tolist()
    return data


def _without_iso(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _without_iso(v) for k, v in value.items() if k != "iso"}
    if isinstance(value, list):
        return [_without_iso(v) for v in value]
    return value


# --- recordings -------------------------------------------------------------------------------


def _write_samples(writer: Any, samples: list[Sample], ts: Typestore, serialize: Any) -> None:
    """Each sample into a rosbags writer (ROS 1 or rosbag2), one connection per topic."""
    connections = {}
    for sample in samples:
        msgtype = ros2_type(sample.ros_type)
        if sample.topic not in connections:
            connections[sample.topic] = writer.add_connection(sample.topic, msgtype, typestore=ts)
        writer.write(connections[sample.topic], sample.stamp_ns, serialize(sample.msg, msgtype))


def write_ros1_bag(path: Path, samples: list[Sample], ts: Typestore) -> Path:
    from rosbags.rosbag1 import Writer

    with Writer(path) as writer:
        _write_samples(writer, samples, ts, ts.serialize_ros1)
    return path


def write_ros2_bag(folder: Path, samples: list[Sample], ts: Typestore, *, mcap: bool) -> Path:
    """A rosbag2 folder; returns the path of its one storage file (.db3 or .mcap)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    with Writer(folder, version=9, storage_plugin=plugin) as writer:
        _write_samples(writer, samples, ts, ts.serialize_cdr)
    (storage,) = [p for p in folder.iterdir() if p.suffix in (".db3", ".mcap")]
    return storage
