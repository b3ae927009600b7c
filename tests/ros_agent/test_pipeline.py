"""The warning every agent (ROS 1, ROS 2, import) gives when the robot token would travel in
clear."""

import pytest

from ros_agent.pipeline import token_in_clear


@pytest.mark.parametrize(
    ("url", "host"),
    [
        ("https://portal.example.org", None),
        ("http://127.0.0.1:8000", None),
        ("http://localhost:8000", None),
        ("http://[::1]:8000", None),
        ("http://portal.example.org", "portal.example.org"),
        ("http://10.0.0.5:8000", "10.0.0.5"),
    ],
)
def test_the_token_travels_in_clear_over_plain_http_beyond_this_machine(url, host):
    assert token_in_clear(url) == host
