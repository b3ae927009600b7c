"""Fixtures of the page tests: owners with or without chain work, uploads, payloads."""

import base64
import json
import struct
import uuid
import zlib
from datetime import UTC, datetime

import pytest
from django.test import Client

from accounts.keyexchange import portal_sm2_public_key
from accounts.models import Owner
from accounts.services.owners import owner_create
from sharing.models import Record
from sharing.services.uploads import record_create
from smcrypto import sm2, sm4
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup


def encrypted_key(key: bytes) -> str:
    """What the page's script submits: the SM4 key encrypted to the portal's SM2 key."""
    return sm2.encrypt(portal_sm2_public_key(), key)


@pytest.fixture
def pending_owner(db):
    """An owner whose chain work is never run: for pages that do not need the chain."""

    def make(username: str | None = None, *, key: bytes | None = None) -> Owner:
        return owner_create(
            username=username or f"owner-{uuid.uuid4().hex[:8]}",
            password=TEST_PASSWORD,
            sm4_key=key or sm4.generate_key(),
        )

    return make


@pytest.fixture
def login(client):
    """The test client, logged in as an owner (or any user)."""

    def as_(who: object) -> Client:
        client.force_login(getattr(who, "user", who))
        return client

    return as_


@pytest.fixture
def upload(django_capture_on_commit_callbacks):
    """Upload an envelope as the robot would; anchoring runs inline."""

    def send(setup: RobotSetup, seq: int, *, anchor: bool = True, **kwargs: object) -> Record:
        data = setup.seal(seq, **kwargs)
        if not anchor:
            return record_create(robot=setup.robot, data=data)
        with django_capture_on_commit_callbacks(execute=True):
            record = record_create(robot=setup.robot, data=data)
        record.refresh_from_db()
        return record

    return send


def fig4(owner: str, data_type: str, topic: str, data: dict) -> bytes:
    """The paper's Fig. 4 record, as ros_agent.wrapping.record_json makes it."""
    record = {
        "K": data,
        "Owner": owner,
        "Time": datetime.now(tz=UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
        "Type": data_type,
        "Topic": topic,
    }
    return json.dumps(record, separators=(",", ":")).encode()


def odometry(owner: str, x: float, y: float, *, marker: str = "odom-frame") -> bytes:
    return fig4(
        owner,
        "nav_msgs/Odometry",
        "/robot/odom",
        {
            "header": {"seq": 1, "stamp": {"secs": 1, "nsecs": 0, "iso": "x"}, "frame_id": marker},
            "child_frame_id": "base_link",
            "position": {"x": x, "y": y, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.38268343, "w": 0.92387953},
            "linear_velocity": {"x": 0.5, "y": 0.0, "z": 0.0},
            "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.1},
            "pose_covariance": [0.0] * 36,
            "twist_covariance": [0.0] * 36,
        },
    )


def tiny_png(width: int = 4, height: int = 3) -> bytes:
    rows = b"".join(b"\x00" + bytes([200, 30, 30] * width) for _ in range(height))

    def chunk(tag: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + tag + body + struct.pack(">I", zlib.crc32(tag + body))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows))
        + chunk(b"IEND", b"")
    )


def image(owner: str) -> bytes:
    return fig4(
        owner,
        "sensor_msgs/Image",
        "/robot/complicatedImage",
        {
            "header": {"seq": 1, "stamp": {"secs": 1, "nsecs": 0, "iso": "x"}, "frame_id": "cam"},
            "width": 4,
            "height": 3,
            "encoding": "rgb8",
            "format": "png",
            "data": base64.b64encode(tiny_png()).decode(),
        },
    )
