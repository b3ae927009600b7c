"""The contract's values as the client writes them: record ids, ROS types and capture times."""

import uuid
from datetime import UTC, datetime

import pytest

from chainworker.codec import (
    bytes32_to_data_type,
    bytes32_to_record_id,
    chain_time_to_datetime,
    data_type_to_bytes32,
    datetime_to_chain_time,
    record_id_to_bytes32,
)


def test_record_id_is_uuid_left_aligned_and_zero_padded():
    record_id = uuid.UUID("12345678-1234-5678-1234-567812345678")
    raw = record_id_to_bytes32(record_id)
    assert raw == record_id.bytes + bytes(16)
    assert bytes32_to_record_id(raw) == record_id


def test_data_type_fits_or_is_hashed():
    assert data_type_to_bytes32("nav_msgs/Odometry") == b"nav_msgs/Odometry".ljust(32, b"\0")
    assert bytes32_to_data_type(data_type_to_bytes32("sensor_msgs/Image")) == "sensor_msgs/Image"
    long_type = "geometry_msgs/PoseWithCovarianceStamped"
    hashed = data_type_to_bytes32(long_type)
    assert len(hashed) == 32
    assert hashed != long_type.encode()[:32]
    with pytest.raises(ValueError, match="non-empty"):
        data_type_to_bytes32("")


def test_chain_time_keeps_microseconds():
    moment = datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC)
    assert chain_time_to_datetime(datetime_to_chain_time(moment)) == moment
    with pytest.raises(ValueError, match="timezone"):
        datetime_to_chain_time(datetime(2026, 1, 1))
