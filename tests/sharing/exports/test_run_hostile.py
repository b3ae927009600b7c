"""Issue 38: a record the MCAP builder cannot encode as its ROS type goes to the JSON channel
as its sealed Fig. 4 record, and never fails the export: out-of-range integers, a null (the
agent's NaN) or a float in an integer field, oversized or wrong-length arrays and wrong types,
for each type the builder writes field by field and for types built from their definition.
"""

import base64
import io
import json

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from authros_verify import ChainReader, verify
from authros_verify.messages import message_encode
from sharing.exports.create import export_create
from sharing.models import Export
from sharing.services.uploads import record_create_batch
from tests.authros_verify.conftest import export_files

STAMP = {"secs": 1_777_000_000, "nsecs": 5}
HEADER = {"seq": 0, "stamp": STAMP, "frame_id": "f"}
VECTOR = {"x": 0.0, "y": 0.0, "z": 0.0}
QUATERNION = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}


def _png(width: int, height: int) -> str:
    ok, png = cv2.imencode(".png", np.zeros((height, width, 3), np.uint8))
    assert ok
    return base64.b64encode(png.tobytes()).decode()


def odometry(**changed: object) -> dict:
    return {
        "header": HEADER,
        "child_frame_id": "base",
        "position": VECTOR,
        "orientation": QUATERNION,
        "linear_velocity": VECTOR,
        "angular_velocity": VECTOR,
        "pose_covariance": [0.0] * 36,
        "twist_covariance": [0.0] * 36,
        **changed,
    }


def imu(**changed: object) -> dict:
    return {
        "header": HEADER,
        "orientation": QUATERNION,
        "orientation_covariance": [0.0] * 9,
        "angular_velocity": VECTOR,
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": VECTOR,
        "linear_acceleration_covariance": [0.0] * 9,
        **changed,
    }


def image(**changed: object) -> dict:
    return {
        "header": HEADER,
        "width": 4,
        "height": 3,
        "encoding": "rgb8",
        "format": "png",
        "data": _png(4, 3),
        **changed,
    }


def compressed(**changed: object) -> dict:
    return {"header": HEADER, "format": "jpeg", "data": base64.b64encode(b"\xff\xd8").decode()}


GOOD = [
    ("nav_msgs/Odometry", odometry()),
    ("sensor_msgs/Imu", imu()),
    ("sensor_msgs/Image", image()),
    ("sensor_msgs/CompressedImage", compressed()),
    ("std_msgs/Int32", {"data": 2**31 - 1}),
    ("std_msgs/UInt64", {"data": 2**64 - 1}),
]

HOSTILE = {
    # issue 38's own case: struct.error in the CDR writer before
    "int32 of 2**40": ("std_msgs/Int32", {"data": 2**40}),
    "int32 below its range": ("std_msgs/Int32", {"data": -(2**31) - 1}),
    "uint8 of -1": ("std_msgs/UInt8", {"data": -1}),
    "uint8 of 300": ("std_msgs/UInt8", {"data": 300}),
    "int64 of 2**70": ("std_msgs/Int64", {"data": 2**70}),
    "uint64 of 2**64": ("std_msgs/UInt64", {"data": 2**64}),
    "char of 300": ("std_msgs/Char", {"data": 300}),
    "int8 of 128": ("std_msgs/Int8", {"data": 128}),
    "null (NaN) in an int32": ("std_msgs/Int32", {"data": None}),
    "a float in an int32": ("std_msgs/Int32", {"data": 1.5}),
    "a string in an int32": ("std_msgs/Int32", {"data": "7"}),
    "float32 beyond its range": ("std_msgs/Float32", {"data": 1e300}),
    "int32 array element of 2**40": (
        "std_msgs/Int32MultiArray",
        {"layout": {"dim": [], "data_offset": 0}, "data": [1, 2**40]},
    ),
    "uint32 data_offset of 2**40": (
        "std_msgs/Int32MultiArray",
        {"layout": {"dim": [], "data_offset": 2**40}, "data": [1]},
    ),
    "byte array element of 256": (
        "std_msgs/ByteMultiArray",
        {"layout": {"dim": [], "data_offset": 0}, "data": [256]},
    ),
    "bool that is 1": ("std_msgs/Bool", {"data": 1}),
    "string that is a number": ("std_msgs/String", {"data": 5}),
    "header stamp of 2**40 s": ("std_msgs/Header", {"stamp": {"secs": 2**40, "nsecs": 0}}),
    "odometry: 37 covariances": ("nav_msgs/Odometry", odometry(pose_covariance=[0.0] * 37)),
    "odometry: 10**6 covariances": (
        "nav_msgs/Odometry",
        odometry(twist_covariance=[0.0] * 1_000_000),
    ),
    "odometry: null nanoseconds": (
        "nav_msgs/Odometry",
        odometry(header={**HEADER, "stamp": {"secs": 1, "nsecs": None}}),
    ),
    "odometry: stamp of 2**40 s": (
        "nav_msgs/Odometry",
        odometry(header={**HEADER, "stamp": {"secs": 2**40, "nsecs": 0}}),
    ),
    "odometry: a text position": ("nav_msgs/Odometry", odometry(position={"x": "1"})),
    "imu: 10 covariances": ("sensor_msgs/Imu", imu(orientation_covariance=[0.0] * 10)),
    "imu: float seconds": (
        "sensor_msgs/Imu",
        imu(header={**HEADER, "stamp": {"secs": 1.5, "nsecs": 0}}),
    ),
    "imu: a list for a vector": ("sensor_msgs/Imu", imu(angular_velocity=[0, 0, 0])),
    "image: width 2**40": ("sensor_msgs/Image", image(width=2**40)),
    "image: larger than stated": ("sensor_msgs/Image", image(data=_png(40, 30))),
    "image: a small PNG stated as 100000 x 100000": (
        "sensor_msgs/Image",
        image(width=100_000, height=100_000),
    ),
    "image: null height": ("sensor_msgs/Image", image(height=None)),
    "image: data not base64": ("sensor_msgs/Image", image(data="%%%")),
    "compressed: data a number": ("sensor_msgs/CompressedImage", {**compressed(), "data": 5}),
    "compressed: stamp of -2**40 s": (
        "sensor_msgs/CompressedImage",
        {**compressed(), "header": {**HEADER, "stamp": {"secs": -(2**40), "nsecs": 0}}},
    ),
}


def fig4(data_type: str, data: object) -> bytes:
    record = {"K": data, "Owner": "alice", "Time": "2026-05-01T12:00:00Z", "Type": data_type}
    return json.dumps(record, separators=(",", ":")).encode()


@pytest.mark.parametrize("case", list(HOSTILE))
def test_a_record_that_does_not_fit_its_type_is_its_fig4_record_as_json(case):
    data_type, data = HOSTILE[case]
    plaintext = fig4(data_type, data)
    message = message_encode(data_type=data_type, plaintext=plaintext)
    assert (message.message_encoding, message.schema_encoding) == ("json", "jsonschema")
    assert message.data == plaintext  # the sealed record, byte for byte


@pytest.mark.parametrize(("data_type", "data"), GOOD)
def test_the_same_types_in_range_are_still_cdr(data_type, data):
    message = message_encode(data_type=data_type, plaintext=fig4(data_type, data))
    assert message.message_encoding == "cdr"


def test_nan_in_json_is_kept_as_raw_bytes():
    plaintext = b'{"K":{"data":NaN},"Type":"std_msgs/Int32"}'
    message = message_encode(data_type="std_msgs/Int32", plaintext=plaintext)
    assert message.message_encoding == "json"
    assert json.loads(message.data) == {"raw_base64": base64.b64encode(plaintext).decode()}


@pytest.mark.django_db
def test_hostile_records_land_on_json_channels_and_the_export_succeeds(
    make_robot, deployed, django_capture_on_commit_callbacks
):
    setup = make_robot("alice")
    cases = [*GOOD, *HOSTILE.values()]
    envelopes = [
        setup.seal(
            seq,
            topic=f"/t{seq}",
            data_type=data_type,
            time=f"2026-05-01T12:00:{seq:02d}Z",
            plaintext=fig4(data_type, data),
        )
        for seq, (data_type, data) in enumerate(cases, start=1)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=setup.owner)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    assert (export.exported, export.excluded) == (len(cases), [])
    mcap, bundle = export_files(export)
    encodings = {
        channel.topic: channel.message_encoding
        for _schema, channel, _message in make_reader(io.BytesIO(mcap)).iter_messages()
    }
    assert [encodings[f"/t{seq}"] for seq in range(1, len(GOOD) + 1)] == ["cdr"] * len(GOOD)
    hostile = range(len(GOOD) + 1, len(cases) + 1)
    assert [encodings[f"/t{seq}"] for seq in hostile] == ["json"] * len(HOSTILE)
    report = verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
