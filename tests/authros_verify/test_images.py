"""Images from the agent's extractor to the verifier's ROS 2 message, both through Pillow (no
OpenCV on a robot or an auditor's machine): every encoding the agent reads comes back as the
same pixels in the same channel order, and a PNG that is not what its record states (other
pixels, broken, cut short) goes on a JSON channel instead of into a wrong image."""

import base64
import io
import json
import zlib

import numpy as np
import pytest
from PIL import Image
from rosbags.typesys import Stores, get_typestore

from authros_verify.messages import message_encode
from ros_agent.extractors import IMAGE_ENCODINGS, image

pytestmark = pytest.mark.nodb

HEADER = {"seq": 1, "stamp": {"secs": 1, "nsecs": 5}, "frame_id": "camera"}
TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)


class RosImage:
    """A sensor_msgs/Image as rospy gives it (only what the extractor reads)."""

    def __init__(self, pixels: np.ndarray, encoding: str) -> None:
        height, width = pixels.shape[:2]
        self.header = type("Header", (), {"seq": 1, "frame_id": "camera"})()
        self.header.stamp = type("Time", (), {"secs": 1, "nsecs": 5})()
        self.height, self.width, self.encoding = height, width, encoding
        self.is_bigendian = 0
        self.step = pixels[0].nbytes
        self.data = pixels.astype(pixels.dtype.newbyteorder("<")).tobytes()


def _pixels(encoding: str, height: int = 6, width: int = 5) -> np.ndarray:
    element, channels, _ = IMAGE_ENCODINGS[encoding]
    shape = (height, width) if channels == 1 else (height, width, channels)
    return np.random.default_rng(7).integers(0, np.iinfo(element).max, shape, dtype=element)


def _record(data: dict) -> bytes:
    record = {"K": data, "Owner": "alice", "Time": "2026-05-01T12:00:00Z"}
    return json.dumps({**record, "Type": "sensor_msgs/Image"}).encode()


def _png(pixels: np.ndarray, mode: str | None = None) -> str:
    out = io.BytesIO()
    picture = Image.fromarray(pixels)
    (picture.convert(mode) if mode else picture).save(out, format="PNG")
    return base64.b64encode(out.getvalue()).decode()


@pytest.mark.parametrize("encoding", sorted(IMAGE_ENCODINGS))
def test_each_encoding_comes_back_as_the_robots_pixels(encoding):
    pixels = _pixels(encoding)
    data = image(RosImage(pixels, encoding))
    message = message_encode(data_type="sensor_msgs/Image", plaintext=_record(data))
    assert message.message_encoding == "cdr"
    decoded = TYPESTORE.deserialize_cdr(message.data, "sensor_msgs/msg/Image")
    assert (decoded.encoding, decoded.height, decoded.width) == (encoding, 6, 5)
    raw = np.frombuffer(decoded.data.tobytes(), pixels.dtype.newbyteorder("<"))
    assert np.array_equal(raw.reshape(pixels.shape), pixels)


def test_the_png_holds_the_true_colours_whatever_the_order_of_the_robots_channels():
    red = np.zeros((2, 2, 3), np.uint8)
    red[..., 2] = 255  # red in bgr8
    data = image(RosImage(red, "bgr8"))
    with Image.open(io.BytesIO(base64.b64decode(data["data"]))) as png:
        assert png.mode == "RGB"
        assert png.getpixel((0, 0)) == (255, 0, 0)


def _cut_short(encoding: str) -> str:
    whole = base64.b64decode(image(RosImage(_pixels(encoding, 60, 50), encoding))["data"])
    return base64.b64encode(whole[: len(whole) // 2]).decode()


def _bad_data_stream() -> str:
    whole = bytearray(base64.b64decode(_png(_pixels("rgb8"))))
    at = whole.index(b"IDAT") + 4
    whole[at : at + 8] = zlib.compress(b"x")[:8][::-1]
    return base64.b64encode(bytes(whole)).decode()


def _png_of_48_bit_rgb(height: int = 6, width: int = 5) -> str:
    """A PNG of 16 bits a channel (Pillow reads it as 8-bit RGB, losing the low bytes)."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body).to_bytes(4, "big")
        return len(body).to_bytes(4, "big") + kind + body + crc

    header = width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([16, 2, 0, 0, 0])
    rows = b"".join(b"\x00" + bytes(range(width * 6)) for _ in range(height))
    body = chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")
    return base64.b64encode(b"\x89PNG\r\n\x1a\n" + body).decode()


MISFITS = {
    "48-bit RGB PNG stated as rgb8": ("rgb8", _png_of_48_bit_rgb),
    "grey PNG stated as rgb8": ("rgb8", lambda: _png(_pixels("mono8"))),
    "RGB PNG stated as mono8": ("mono8", lambda: _png(_pixels("rgb8"))),
    "RGBA PNG stated as rgb8": ("rgb8", lambda: _png(_pixels("rgba8"))),
    "8-bit grey stated as mono16": ("mono16", lambda: _png(_pixels("mono8"))),
    "palette PNG stated as rgb8": ("rgb8", lambda: _png(_pixels("rgb8"), "P")),
    "a PNG cut short": ("rgb8", lambda: _cut_short("rgb8")),
    "a broken data stream": ("rgb8", _bad_data_stream),
    "not a PNG": ("rgb8", lambda: base64.b64encode(b"GIF89a" + bytes(40)).decode()),
}


@pytest.mark.parametrize("case", sorted(MISFITS))
def test_a_png_that_is_not_what_its_record_states_goes_on_a_json_channel(case):
    encoding, data = MISFITS[case]
    height, width = (60, 50) if "cut short" in case else (6, 5)
    record = {"header": HEADER, "height": height, "width": width, "encoding": encoding}
    plaintext = _record({**record, "format": "png", "data": data()})
    message = message_encode(data_type="sensor_msgs/Image", plaintext=plaintext)
    assert message.message_encoding == "json"
    assert message.data == plaintext
