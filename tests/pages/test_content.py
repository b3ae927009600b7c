"""How a decrypted record is shown (sharing/content.py): pure functions of its plaintext."""

import base64
import json

import pytest

from sharing.content import (
    MISSING,
    content_of,
    image_data_url,
    odometry_rows,
)
from tests.pages.conftest import image, odometry, tiny_png

pytestmark = pytest.mark.nodb


def test_odometry_record_gets_its_rows_and_pretty_json():
    content = content_of(data_type="nav_msgs/Odometry", plaintext=odometry("alice", 1.5, -2.0))
    assert content.is_odometry
    rows = dict(content.odometry)
    assert rows["Frame"] == "odom-frame to base_link"
    assert rows["Position (m)"] == "x 1.5000, y -2.0000, z 0.0000"
    assert rows["Heading (yaw)"] == "45.0°"
    assert json.loads(content.pretty)["K"]["position"] == {"x": 1.5, "y": -2.0, "z": 0.0}
    assert content.image_url == ""


def test_image_record_shows_its_image_and_leaves_the_base64_out_of_the_json():
    content = content_of(data_type="sensor_msgs/Image", plaintext=image("alice"))
    encoded = base64.b64encode(tiny_png()).decode()
    assert content.image_url == f"data:image/png;base64,{encoded}"
    assert content.image_size == (4, 3)
    assert encoded not in content.pretty
    assert "base64 characters, above" in content.pretty


def test_anything_but_json_is_shown_as_raw_text_with_the_reason():
    content = content_of(data_type="std_msgs/String", plaintext=b"\xff\xfenot json")
    assert content.document is None
    assert content.pretty == ""
    assert content.problem == "it is not UTF-8 text"
    assert content.raw == "\ufffd\ufffdnot json"
    assert content.size == content.raw_shown_bytes == 10
    assert not content.raw_truncated


@pytest.mark.parametrize(
    "encoded",
    [None, 5, "not base64!", base64.b64encode(b"GIF89a....").decode(), ""],
)
def test_only_png_and_jpeg_become_data_urls(encoded):
    assert image_data_url(encoded) == ""


def test_a_jpeg_becomes_a_data_url():
    encoded = base64.b64encode(b"\xff\xd8\xff\xe0rest").decode()
    assert image_data_url(encoded) == f"data:image/jpeg;base64,{encoded}"


def test_odometry_rows_of_partial_or_odd_data_say_what_is_missing():
    rows = dict(odometry_rows({"position": {"x": True, "y": "1", "z": 2}, "header": "odd"}))
    assert rows["Position (m)"] == f"x {MISSING}, y {MISSING}, z 2.0000"
    assert rows["Heading (yaw)"] == MISSING
    assert rows["Stamp"] == MISSING


def test_the_record_formats_fields_are_labelled_and_k_is_the_data():
    """The paper's record format named (issue 48): Owner, Time, Type and Topic labelled, and K
    shown as the data, not a bare "K" wrapping everything."""
    content = content_of(data_type="nav_msgs/Odometry", plaintext=odometry("alice", 1.5, -2.0))
    fields = dict(content.fields)
    assert fields["Owner (Owner)"] == "alice"
    assert fields["ROS message type (Type)"] == "nav_msgs/Odometry"
    assert fields["Topic (Topic)"] == "/robot/odom"
    assert "Captured, UTC (Time)" in fields
    assert json.loads(content.data_pretty)["position"] == {"x": 1.5, "y": -2.0, "z": 0.0}
    # An image's K keeps its pixels out of the data shown, as the whole record's JSON does.
    shown = content_of(data_type="sensor_msgs/Image", plaintext=image("alice"))
    assert "base64 characters, above" in json.loads(shown.data_pretty)["data"]
    # Not the record format: no fields claimed.
    other = content_of(data_type="std_msgs/String", plaintext=b'{"data": "hi"}')
    assert (other.fields, other.data_pretty) == ([], "")
