"""A record's line is parsed once, without the duplicate-field hook, and taken only when it is
its entry's one serialisation: a field twice, a fraction, NaN or a changed spacing is not (the
bundle is then read whole, and the record on that line named). The batch signature read from a
line is a hint for where to cut chunks, never trusted."""

import contextlib

import pytest

from authros_verify.bundle import bundle_entry_line
from authros_verify.check import _batch_hint, _canonical_entry, _strict_json

ENTRY = {
    "record": "1b4e28ba-2fa1-11d2-883f-0016d3cca427",
    "seq": 7,
    "signature": {"public_key": "04" + "ab" * 64, "sig": "cd" * 64, "signer": "ef" * 32},
    "topic": "/odom",
}
LINE = bundle_entry_line(ENTRY).encode("ascii")


def test_a_line_in_its_canonical_form_is_its_entry():
    assert _canonical_entry(LINE) == ENTRY
    assert _canonical_entry(LINE) == _strict_json(LINE)


@pytest.mark.parametrize(
    "changed",
    [
        LINE.replace(b'"seq":7', b'"seq":7,"seq":7'),  # a field twice, the same value
        LINE.replace(b'"seq":7', b'"seq":8,"seq":7'),  # a field twice, the last kept
        LINE.replace(b'"topic":"/odom"', b'"topic":"/odom","record":"x"'),
        LINE.replace(b'"seq":7', b'"seq":7.0'),  # a fraction, kept as its text
        LINE.replace(b'"seq":7', b'"seq":7e0'),
        LINE.replace(b'"seq":7', b'"seq": 7'),  # spacing
        LINE.replace(b'"/odom"', b'"\\/odom"'),  # another spelling of the same string
    ],
)
def test_a_line_not_in_its_canonical_form_is_refused(changed):
    assert changed != LINE
    with contextlib.suppress(ValueError):  # not JSON at all: refused as well
        assert _canonical_entry(changed) is None


@pytest.mark.parametrize("constant", [b"NaN", b"Infinity", b"-Infinity"])
def test_nan_and_infinity_are_refused(constant):
    with pytest.raises(ValueError, match="is not a number JSON allows"):
        _canonical_entry(LINE.replace(b'"seq":7', b'"seq":' + constant))


def test_a_field_twice_is_still_refused_when_the_bundle_is_read_whole():
    with pytest.raises(ValueError, match="twice"):
        _strict_json(LINE.replace(b'"seq":7', b'"seq":7,"seq":7'))


def test_the_batch_hint_is_the_lines_sig_or_none():
    assert _batch_hint(LINE) == b"cd" * 64
    assert _batch_hint(bundle_entry_line({"record": "x", "signature": None}).encode()) is None
