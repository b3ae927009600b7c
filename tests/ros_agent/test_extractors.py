"""Extractors on real genpy messages (Debian's nav_msgs, sensor_msgs, std_msgs, geometry_msgs)."""

import base64
import json
import math

import cv2
import genpy
import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from sensor_msgs.msg import CompressedImage, Image, Imu
from std_msgs.msg import Duration, MultiArrayDimension, String, UInt8MultiArray

from ros_agent import extractors
from ros_agent.extractors import ExtractionError, extract

STAMP = genpy.Time(1795272613, 728813456)
STAMP_ISO = "2026-11-21T14:50:13.728813Z"


def _png_pixels(record: dict) -> np.ndarray:
    assert record["format"] == "png"
    png = np.frombuffer(base64.b64decode(record["data"]), np.uint8)
    return cv2.imdecode(png, cv2.IMREAD_UNCHANGED)


def _image(pixels: np.ndarray, encoding: str, *, padding: int = 0, bigendian: bool = False):
    height, width = pixels.shape[:2]
    row = pixels.reshape(height, -1)
    if bigendian:
        row = row.astype(row.dtype.newbyteorder(">"))
    row_bytes = row.view(np.uint8).reshape(height, -1)
    padded = np.concatenate([row_bytes, np.full((height, padding), 0xAB, np.uint8)], axis=1)
    msg = Image(height=height, width=width, encoding=encoding, is_bigendian=int(bigendian))
    msg.header.stamp = STAMP
    msg.header.frame_id = "camera"
    msg.step = padded.shape[1]
    msg.data = padded.tobytes()
    return msg


def _random_pixels(shape: tuple[int, ...], dtype: type = np.uint8) -> np.ndarray:
    high = np.iinfo(dtype).max + 1
    return np.random.default_rng(7).integers(0, high, shape, dtype=dtype)


def test_odometry_has_stamp_frames_pose_and_twist():
    msg = Odometry()
    msg.header.seq = 5
    msg.header.stamp = STAMP
    msg.header.frame_id = "odom"
    msg.child_frame_id = "base_link"
    msg.pose.pose.position.x, msg.pose.pose.position.y = 1.25, -2.5
    msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(0.5), math.cos(0.5)
    msg.twist.twist.linear.x = 0.75
    msg.twist.twist.angular.z = -0.1
    msg.pose.covariance = [0.0] * 35 + [float("nan")]

    data = extract(msg, "nav_msgs/Odometry")

    assert data["header"] == {
        "seq": 5,
        "stamp": {"secs": 1795272613, "nsecs": 728813456, "iso": STAMP_ISO},
        "frame_id": "odom",
    }
    assert data["child_frame_id"] == "base_link"
    assert data["position"] == {"x": 1.25, "y": -2.5, "z": 0.0}
    assert data["orientation"] == {"x": 0.0, "y": 0.0, "z": math.sin(0.5), "w": math.cos(0.5)}
    assert data["linear_velocity"] == {"x": 0.75, "y": 0.0, "z": 0.0}
    assert data["angular_velocity"] == {"x": 0.0, "y": 0.0, "z": -0.1}
    assert data["pose_covariance"][-1] is None  # NaN has no JSON form
    json.dumps(data, allow_nan=False)


@pytest.mark.parametrize(
    ("encoding", "shape", "dtype", "to_bgr"),
    [
        ("rgb8", (5, 7, 3), np.uint8, lambda p: p[..., ::-1]),
        ("bgr8", (5, 7, 3), np.uint8, lambda p: p),
        ("mono8", (6, 9), np.uint8, lambda p: p),
        ("16UC1", (4, 6), np.uint16, lambda p: p),
    ],
)
@pytest.mark.parametrize("padding", [0, 5])
def test_image_becomes_a_lossless_png(encoding, shape, dtype, to_bgr, padding):
    pixels = _random_pixels(shape, dtype)
    data = extract(_image(pixels, encoding, padding=padding), "sensor_msgs/Image")

    assert (data["width"], data["height"], data["encoding"]) == (shape[1], shape[0], encoding)
    assert data["header"]["stamp"]["iso"] == STAMP_ISO
    decoded = _png_pixels(data)
    assert decoded.dtype == dtype
    np.testing.assert_array_equal(decoded, to_bgr(pixels))


def test_big_endian_16bit_image_is_read_in_its_byte_order():
    pixels = np.array([[1, 256, 65535], [4660, 0, 43981]], np.uint16)
    msg = _image(pixels, "16UC1", padding=2, bigendian=True)
    assert msg.data[:2] == b"\x00\x01"  # really big-endian on the wire

    np.testing.assert_array_equal(_png_pixels(extract(msg, "sensor_msgs/Image")), pixels)


def test_image_data_given_as_a_list_of_ints_is_accepted():
    pixels = _random_pixels((2, 3))
    msg = _image(pixels, "mono8")
    msg.data = list(msg.data)

    np.testing.assert_array_equal(_png_pixels(extract(msg, "sensor_msgs/Image")), pixels)


def test_unsupported_or_inconsistent_images_are_refused_clearly():
    msg = _image(_random_pixels((2, 2, 3)), "bgr8")
    msg.encoding = "bayer_rggb8"
    with pytest.raises(ExtractionError, match="encoding 'bayer_rggb8' is not supported"):
        extract(msg, "sensor_msgs/Image")

    short = _image(_random_pixels((4, 4)), "mono8")
    short.data = short.data[:-1]
    with pytest.raises(ExtractionError, match="need 16"):
        extract(short, "sensor_msgs/Image")

    narrow = _image(_random_pixels((4, 4, 3)), "rgb8")
    narrow.step = 4
    with pytest.raises(ExtractionError, match="step 4 is below"):
        extract(narrow, "sensor_msgs/Image")


def test_compressed_image_keeps_its_bytes():
    ok, jpeg = cv2.imencode(".jpg", _random_pixels((8, 8, 3)))
    assert ok
    msg = CompressedImage(format="jpeg", data=jpeg.tobytes())
    msg.header.stamp = STAMP

    data = extract(msg, "sensor_msgs/CompressedImage")

    assert data["format"] == "jpeg"
    assert base64.b64decode(data["data"]) == jpeg.tobytes()
    assert data["header"]["stamp"]["iso"] == STAMP_ISO


def test_imu_has_orientation_rates_accelerations_and_covariances():
    msg = Imu()
    msg.header.stamp = STAMP
    msg.orientation.w = 1.0
    msg.angular_velocity.z = 0.2
    msg.linear_acceleration.z = 9.81
    msg.orientation_covariance = [-1.0] + [0.0] * 8  # REP 145: -1 means "no orientation"

    data = extract(msg, "sensor_msgs/Imu")

    assert data["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
    assert data["angular_velocity"]["z"] == 0.2
    assert data["linear_acceleration"]["z"] == 9.81
    assert data["orientation_covariance"][0] == -1.0
    assert len(data["linear_acceleration_covariance"]) == 9


def test_string():
    assert extract(String(data="héllo"), "std_msgs/String") == {"data": "héllo"}


def test_any_other_type_is_converted_field_by_field():
    msg = PoseStamped()
    msg.header.seq = 3
    msg.header.stamp = STAMP
    msg.header.frame_id = "map"
    msg.pose.position.x = 1.5
    msg.pose.orientation.w = 1.0

    assert extract(msg, "geometry_msgs/PoseStamped") == {
        "header": {
            "seq": 3,
            "stamp": {"secs": 1795272613, "nsecs": 728813456, "iso": STAMP_ISO},
            "frame_id": "map",
        },
        "pose": {
            "position": {"x": 1.5, "y": 0.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
    }


def test_generic_conversion_of_durations_byte_arrays_and_nested_arrays():
    array = UInt8MultiArray(data=bytes([0, 1, 254, 255]))
    array.layout.dim = [MultiArrayDimension(label="x", size=4, stride=4)]
    assert extract(array, "std_msgs/UInt8MultiArray") == {
        "layout": {"dim": [{"label": "x", "size": 4, "stride": 4}], "data_offset": 0},
        "data": base64.b64encode(bytes([0, 1, 254, 255])).decode(),
    }
    assert extract(Duration(data=genpy.Duration(3, 5)), "std_msgs/Duration") == {
        "data": {"secs": 3, "nsecs": 5}
    }


def test_iso_utc_and_stamps_keep_microseconds():
    assert extractors.iso_utc(extractors.stamp_datetime(genpy.Time(0, 999))) == (
        "1970-01-01T00:00:00.000000Z"
    )
    assert extractors.stamp_datetime(STAMP).microsecond == 728813
