"""A robot's custom ROS 2 message, nested three deep: authros_test_msgs/Inspection holds
Findings (one, and a sequence of them), each with a Severity, beside a std_msgs/Header, a
geometry_msgs/Point, a fixed float64 array, bytes and constants. Its `.msg` files are in
tests/ros_agent/msgs/ (the layout of a ROS 2 share folder); `inspection` is a sample of it and
`inspection_record` the record data `K` the agent must make of that sample, written out by hand.
"""

import base64
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

MSG_DIR = Path(__file__).resolve().parents[1] / "ros_agent" / "msgs"
INSPECTION = "authros_test_msgs/Inspection"  # as agent.yaml names it
INSPECTION_TOPIC = "/robot/inspection"
LEARNED = [
    "authros_test_msgs/msg/Finding",
    "authros_test_msgs/msg/Inspection",
    "authros_test_msgs/msg/Severity",
]
_SECS = 1_767_225_600  # 2026-01-01T00:00:00Z


def inspection(typestore: Typestore, index: int) -> Any:
    """The `index`th sample, of a type store that has learned the package's types."""
    t = typestore.types

    def finding(label: str, confidence: float, level: int, box: list[int]) -> Any:
        return t["authros_test_msgs/msg/Finding"](
            label=label,
            confidence=confidence,
            severity=t["authros_test_msgs/msg/Severity"](level=level, note=f"{label} seen"),
            pixel_box=np.array(box, dtype=np.int32),
        )

    return t["authros_test_msgs/msg/Inspection"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=_SECS + index, nanosec=123_456_789),
            frame_id="base_link",
        ),
        site=f"pump room {index}",
        primary=finding("leak", 0.75, 2, [10, 20, 30, 40]),
        findings=[finding("rust", 0.5, 0, [1, 2, 3, 4]), finding("crack", 0.25, 2, [])],
        where=t["geometry_msgs/msg/Point"](x=1.5, y=-2.25, z=float(index)),
        calibration=np.array([0.001, 2.0, -3.5], dtype=np.float64),
        snapshot=np.frombuffer(bytes([index, 0, 255, 7]), dtype=np.uint8),
        round=2**40 + index,
        complete=index % 2 == 0,
        mode=1,
    )


def inspection_record(index: int) -> dict:
    """The record data of `inspection(index)`: every field, as the generic walk writes it."""

    def finding(label: str, confidence: float, level: int, box: list[int]) -> dict:
        return {
            "label": label,
            "confidence": confidence,
            "severity": {"level": level, "note": f"{label} seen"},
            "pixel_box": box,
        }

    return {
        "header": {
            "seq": 0,
            "stamp": {
                "secs": _SECS + index,
                "nsecs": 123_456_789,
                "iso": f"2026-01-01T00:00:{index:02d}.123456Z",
            },
            "frame_id": "base_link",
        },
        "site": f"pump room {index}",
        "primary": finding("leak", 0.75, 2, [10, 20, 30, 40]),
        "findings": [finding("rust", 0.5, 0, [1, 2, 3, 4]), finding("crack", 0.25, 2, [])],
        "where": {"x": 1.5, "y": -2.25, "z": float(index)},
        "calibration": [0.001, 2.0, -3.5],
        "snapshot": base64.b64encode(bytes([index, 0, 255, 7])).decode("ascii"),
        "round": 2**40 + index,
        "complete": index % 2 == 0,
        "mode": 1,
    }
