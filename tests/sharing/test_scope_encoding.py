"""The scope's canonical bytes and commitment (docs/grants.md), byte for byte: the chain holds
the commitment, so any other encoding of the same scope would refuse every view."""

import uuid
from datetime import UTC, datetime, timedelta

import pytest

from sharing.scope import (
    ALL_RECORDS_COMMITMENT,
    ScopeError,
    scope_commitment,
    scope_encode,
    scope_make,
)
from smcrypto import sm3

ONE, TWO = uuid.UUID(int=1), uuid.UUID(int=2)
SECOND = datetime(1970, 1, 1, 0, 0, 1, tzinfo=UTC)


def test_the_bytes_are_as_documented():
    scope = scope_make(robots=[str(TWO), ONE, ONE], topics=["/b", "/a", "/b"], since=SECOND)
    expected = (
        b"AuthROS/grant-scope/v1"
        + bytes.fromhex("0002")
        + ONE.bytes
        + TWO.bytes
        + bytes.fromhex("0002")
        + bytes.fromhex("0002")
        + b"/a"
        + bytes.fromhex("0002")
        + b"/b"
        + bytes.fromhex("01")
        + (1_000_000).to_bytes(8, "big")
        + bytes(8)
    )
    assert scope_encode(scope) == expected
    assert scope_commitment(scope) == sm3.sm3_digest(expected)
    # The same scope however it is given: order, duplicates, time zone.
    again = scope_make(
        robots=[ONE, TWO],
        topics=["/a", "/b"],
        since=SECOND.astimezone(datetime.now().astimezone().tzinfo),
    )
    assert scope_commitment(again) == scope_commitment(scope)


def test_all_records_is_zero_and_covers_everything():
    scope = scope_make()
    assert scope.is_all
    assert scope_commitment(scope) == ALL_RECORDS_COMMITMENT == b"\0" * 32
    assert scope.covers(robot_id=ONE, topic="/any", captured_at=SECOND)


def test_covers_is_half_open_and_needs_every_term():
    scope = scope_make(robots=[ONE], topics=["/a"], since=SECOND, until=SECOND + timedelta(1))
    inside = {"robot_id": ONE, "topic": "/a", "captured_at": SECOND}
    assert scope.covers(**inside)
    assert not scope.covers(**{**inside, "robot_id": TWO})
    assert not scope.covers(**{**inside, "topic": "/b"})
    assert not scope.covers(**{**inside, "captured_at": SECOND - timedelta(microseconds=1)})
    assert not scope.covers(**{**inside, "captured_at": SECOND + timedelta(1)})


@pytest.mark.parametrize(
    "values",
    [
        {"robots": ["robot-1"]},
        {"topics": [""]},
        {"topics": ["\ud800"]},
        {"topics": ["a\x00"]},
        {"since": SECOND, "until": SECOND},
        {"since": datetime(1969, 12, 31, tzinfo=UTC)},
        {"since": datetime(2026, 1, 1)},  # no time zone
    ],
)
def test_refusals(values):
    with pytest.raises(ScopeError):
        scope_make(**values)
