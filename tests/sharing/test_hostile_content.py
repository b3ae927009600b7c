"""Hostile content (F7): a verified record is still whatever its robot sealed. A record the
pages cannot interpret is shown as raw text with a note, never a 500, for its owner and its
grantees; a series reads no value from it."""

import json
import math
from datetime import timedelta

import pytest
from django.urls import reverse

from sharing.content import (
    IMAGE_TYPES,
    MAX_DEPTH,
    MISSING,
    ODOMETRY,
    RAW_SHOWN_BYTES,
    content_of,
    document_parse,
    image_size,
    odometry_rows,
)
from sharing.series import record_values
from tests.pages.conftest import image, odometry


def _odometry(x: bytes, y: bytes = b"1.0") -> bytes:
    return b'{"K":{"position":{"x":' + x + b',"y":' + y + b',"z":0.0}}}'


# Plaintexts the pages cannot interpret, and why (content.problem starts with it).
UNINTERPRETABLE = {
    "400-digit integer": (_odometry(b"9" * 400), "it holds an integer of 400 digits"),
    "negative 31-digit integer": (_odometry(b"-" + b"1" * 31), "it holds an integer of 31"),
    "5000-digit integer": (_odometry(b"7" * 5000), "it holds an integer of 5000 digits"),
    "1e999": (_odometry(b"1e999"), "it holds 1e999, which is not a finite number"),
    "-1e999": (_odometry(b"1.0", b"-1e999"), "it holds -1e999"),
    # Past what the parse without a call back per number takes (sharing.content._within_bounds).
    "1E+400": (_odometry(b"1E+400"), "it holds 1E+400, which is not a finite number"),
    "1e0309": (_odometry(b"2.5", b"1e0309"), "it holds 1e0309"),
    "NaN": (_odometry(b"NaN"), "it holds NaN"),
    "Infinity": (_odometry(b"Infinity"), "it holds Infinity"),
    "-Infinity": (_odometry(b"-Infinity"), "it holds -Infinity"),
    "10000-deep nesting": (
        b'{"K":' + b"[" * 10_000 + b"]" * 10_000 + b"}",
        f"it is nested more than {MAX_DEPTH} levels deep",
    ),
    # Past the recursion limit json.loads runs with (3000 in the portal, more under pytest).
    "100000-deep nesting": (
        b'{"K":' + b"[" * 100_000 + b"]" * 100_000 + b"}",
        f"it is nested more than {MAX_DEPTH} levels deep",
    ),
    "100-deep nesting": (
        b'{"K":{"position":{"x":1,"y":2},"n":' + b"[" * 100 + b"]" * 100 + b"}}",
        f"it is nested more than {MAX_DEPTH} levels deep",
    ),
    "invalid UTF-8": (b'{"K":{"position":{"x":1,"y":2},"s":"\xff\xfe\xc3"}}', "it is not UTF-8"),
    "binary": (bytes(range(256)), "it is not UTF-8"),
    "truncated JSON": (b'{"K":{"position":{"x":1', "it is not JSON"),
    "empty": (b"", "it is not JSON"),
}

# Plaintexts that are JSON of a shape the pages do not expect: shown as JSON, without a pose.
ODD_SHAPES = {
    "lone surrogate": b'{"K":{"header":{"frame_id":"\\ud800"},"child_frame_id":"\\udfff"}}',
    "wrong types": (
        b'{"K":{"position":[1,2],"orientation":"north","header":7,"child_frame_id":{"a":1},'
        b'"linear_velocity":{"x":true,"y":null,"z":"1"},"angular_velocity":[]}}'
    ),
    "huge finite floats": (
        b'{"K":{"position":{"x":1e308,"y":-1e308},'
        b'"orientation":{"x":1e308,"y":1e308,"z":1e308,"w":1e308}}}'
    ),
    "top-level scalar": b"12",
    "null": b"null",
    "K is a list": b'{"K":[1,2,3]}',
    "30-digit integers": _odometry(b"9" * 30, b"-" + b"9" * 30),
}


def _encodable(text: str) -> bool:
    text.encode("utf-8")  # what the response will do: a lone surrogate raises here
    return True


# --- the pure functions ----------------------------------------------------------------------


@pytest.mark.parametrize("data_type", [ODOMETRY, *sorted(IMAGE_TYPES), "std_msgs/String"])
@pytest.mark.parametrize(("plaintext", "reason"), UNINTERPRETABLE.values(), ids=UNINTERPRETABLE)
def test_a_record_that_cannot_be_interpreted_is_shown_raw_with_the_reason(
    plaintext, reason, data_type
):
    content = content_of(data_type=data_type, plaintext=plaintext)
    assert content.problem.startswith(reason)
    assert content.pretty == ""
    assert content.odometry == []
    assert content.image_url == ""
    assert content.size == len(plaintext)
    assert content.raw_shown_bytes == min(len(plaintext), RAW_SHOWN_BYTES)
    assert content.raw_truncated == (len(plaintext) > RAW_SHOWN_BYTES)
    assert _encodable(content.raw)
    assert record_values(plaintext, ["position.x"]) == [None]


@pytest.mark.parametrize("data_type", [ODOMETRY, *sorted(IMAGE_TYPES)])
@pytest.mark.parametrize("plaintext", ODD_SHAPES.values(), ids=ODD_SHAPES)
def test_json_of_an_odd_shape_is_shown_as_json(plaintext, data_type):
    content = content_of(data_type=data_type, plaintext=plaintext)
    assert content.problem == ""
    assert _encodable(content.pretty)
    for label, value in content.odometry:
        assert _encodable(label)
        assert _encodable(value)
        assert "nan" not in value
        assert "inf" not in value


def test_a_lone_surrogate_is_shown_escaped():
    content = content_of(data_type=ODOMETRY, plaintext=ODD_SHAPES["lone surrogate"])
    assert "\\ud800" in content.pretty
    assert dict(content.odometry)["Frame"] == "\\ud800 to \\udfff"


def test_a_large_record_is_shown_truncated():
    plaintext = b"\xff" + b"x" * (RAW_SHOWN_BYTES * 2)
    content = content_of(data_type=ODOMETRY, plaintext=plaintext)
    assert content.raw_truncated
    assert len(content.raw) == RAW_SHOWN_BYTES


@pytest.mark.parametrize(
    "data",
    [
        None,
        12,
        "text",
        [1, 2],
        {"position": {"x": 10**400, "y": float("nan"), "z": float("inf")}},
        {"orientation": {"x": 10**400, "y": 0, "z": 0, "w": 1}},
        {"orientation": {"x": 1e308, "y": 1e308, "z": 1e308, "w": -1e308}},
        {"header": {"stamp": {"iso": 10**5000}, "frame_id": ["a"]}, "child_frame_id": 10**400},
    ],
)
def test_odometry_rows_take_any_value(data):
    rows = dict(odometry_rows(data))
    assert rows["Heading (yaw)"] == MISSING
    assert "nan" not in "".join(rows.values())


@pytest.mark.parametrize(
    ("width", "height", "expected"),
    [
        (4, 3, (4, 3)),
        (10**400, 3, (None, None)),
        (4, 10**6, (None, None)),
        ("100%", 3, (None, None)),
        (True, 3, (None, None)),
        (0, 3, (None, None)),
        (-4, 3, (None, None)),
        (4.0, 3, (None, None)),
        ({"a": 1}, [1], (None, None)),
    ],
)
def test_an_image_size_is_used_only_when_both_sides_are_plausible(width, height, expected):
    assert image_size(width, height) == expected


@pytest.mark.parametrize("data", [5, None, ["a"], {"b": 1}, "x" * 10])
def test_an_image_record_whose_data_is_not_a_string_has_no_image(data):
    document = json.loads(image("alice"))
    document["K"]["data"] = data
    document["K"]["width"] = 10**25
    content = content_of(data_type="sensor_msgs/Image", plaintext=json.dumps(document).encode())
    assert content.problem == ""
    assert content.image_url == ""
    assert content.image_size == (None, None)


def test_an_image_with_an_implausible_size_is_shown_without_one():
    document = json.loads(image("alice"))
    document["K"]["width"] = 10**25
    content = content_of(data_type="sensor_msgs/Image", plaintext=json.dumps(document).encode())
    assert content.image_url.startswith("data:image/png;base64,")
    assert content.image_size == (None, None)


@pytest.mark.parametrize("plaintext", ODD_SHAPES.values(), ids=ODD_SHAPES)
def test_a_series_value_is_finite_or_none(plaintext):
    values = record_values(plaintext, ["position.x", "position.y", "orientation.w"])
    assert all(value is None or math.isfinite(value) for value in values)


# --- through the pages, for the owner and a grantee ------------------------------------------


PAGE_CASES = [
    "400-digit integer",
    "1e999",
    "NaN",
    "10000-deep nesting",
    "100000-deep nesting",
    "invalid UTF-8",
]


@pytest.mark.django_db
@pytest.mark.parametrize("case", PAGE_CASES)
def test_pages_of_a_hostile_record_and_of_its_topic_answer_200(case, client, alice, bob, upload):
    plaintext, _reason = UNINTERPRETABLE[case]
    upload(alice, 1, plaintext=odometry("alice", 0.0, 0.0))
    hostile = upload(alice, 2, plaintext=plaintext)
    later = upload(alice, 3, plaintext=odometry("alice", 1.0, 1.0))
    assert hostile.status == later.status == "anchored"
    for viewer in (alice.owner, bob):
        client.force_login(viewer.user)
        page = client.get(reverse("record-detail", args=[hostile.id]))
        html = page.content.decode()
        assert page.status_code == 200, (case, viewer)
        assert 'data-verdict="verified"' in html
        assert "This record's content could not be interpreted" in html
        assert 'data-testid="record-raw-text"' in html
        assert 'data-testid="record-json"' not in html

        raw = client.get(reverse("record-raw", args=[hostile.id]))
        assert raw.status_code == 200
        assert raw.content == plaintext

        series = client.get("/api/v1/records/series/", _series_around(later))
        assert series.status_code == 200, (case, viewer)
        body = series.json()
        assert (body["source_records"], body["verified"], body["refused"]) == (3, 3, 0)
        assert body["without_values"] == 1
        assert [point[1:] for point in body["points"]] == [[0.0, 0.0], [1.0, 1.0]]


@pytest.mark.django_db
def test_a_record_page_of_odd_json_answers_200(client, alice, upload):
    record = upload(alice, 1, plaintext=ODD_SHAPES["lone surrogate"])
    wrong = upload(alice, 2, plaintext=ODD_SHAPES["wrong types"])
    client.force_login(alice.owner.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 200
    assert "\\ud800" in page.content.decode()
    page = client.get(reverse("record-detail", args=[wrong.id]))
    assert page.status_code == 200
    assert 'data-testid="odometry-table"' in page.content.decode()
    body = client.get("/api/v1/records/series/", _series_around(wrong)).json()
    assert (body["verified"], body["without_values"], body["points"]) == (2, 2, [])


def _series_around(record) -> dict[str, str]:
    """The series API's query of x and y on the record's topic, a minute either side."""
    return {
        "robot": str(record.robot_id),
        "topic": record.topic,
        "fields": "position.x,position.y",
        "since": (record.captured_at - timedelta(minutes=1)).isoformat(),
        "until": (record.captured_at + timedelta(minutes=1)).isoformat(),
    }


@pytest.mark.parametrize(
    "plaintext",
    [
        odometry("alice", 1.5, -2.25),  # the parse without a call back per number
        _odometry(b"0." + b"5" * 40 + b"e9", b"-" + b"1" * 30),  # with one: 40 digits
        _odometry(b"1.5e300", b"2E-30"),  # with one: a three-digit exponent
        b'{"K":{"position":{"x":3,"y":4},"n":' + b"[" * 62 + b"]" * 62 + b"}}",  # 64 deep
        b'{"K":{"position":{"x":3,"y":4},"s":"' + b"{[" * 40 + b'"}}',  # brackets in a string
    ],
)
def test_a_record_within_the_bounds_parses_as_json_whichever_way_it_is_read(plaintext):
    assert document_parse(plaintext) == json.loads(plaintext)
