"""Exports: the verified records of a selection as MCAP, opened here with the `mcap` library
and the `mcap-ros2-support` decoders (independent of the portal's code), and the proof
bundle checked by authros_verify against the same anvil the portal anchored on.
"""

import base64
import io
import json
import uuid
from datetime import UTC, datetime, timedelta

import cv2
import numpy as np
import pytest
from django.urls import reverse
from django.utils import timezone
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from accounts.models import Robot
from accounts.services.owners import owner_create
from accounts.services.robots import robot_create
from authros_verify import ChainReader, verify
from sharing.exports.create import export_create
from sharing.exports.run import export_run
from sharing.exports.withdraw import exports_sweep
from sharing.models import Access, Credential, Export, Record, Verdict
from sharing.selection import RecordSelection
from sharing.services.uploads import record_create, record_create_batch
from sharing.storage import envelope_storage
from smcrypto import sm2, sm4
from tests.api.conftest import session_client, token_client
from tests.authros_verify.conftest import export_files
from tests.support.robot_setup import TEST_PASSWORD, seal_for
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

EXPORTS = "/api/v1/exports/"
T0 = datetime(2026, 5, 1, 12, 0, 0, 123456, tzinfo=UTC)


def at(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def iso(moment: datetime) -> str:
    return moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def header(moment: datetime, frame: str) -> dict:
    secs = int(moment.timestamp())
    nsecs = moment.microsecond * 1000 + 789  # below the microsecond the envelope keeps
    return {
        "seq": 0,
        "stamp": {"secs": secs, "nsecs": nsecs, "iso": iso(moment)},
        "frame_id": frame,
    }


def fig4(owner: str, data_type: str, topic: str, moment: datetime, data: dict) -> bytes:
    record = {"K": data, "Owner": owner, "Time": iso(moment), "Type": data_type, "Topic": topic}
    return json.dumps(record, separators=(",", ":")).encode()


PIXELS = np.arange(4 * 3 * 3, dtype=np.uint8).reshape(3, 4, 3) * 7  # rgb8, 4x3


def samples(owner: str) -> list[tuple[str, str, datetime, dict]]:
    """(type, topic, capture time, K) of one record of each kind the agent makes."""
    ok, png = cv2.imencode(".png", cv2.cvtColor(PIXELS, cv2.COLOR_RGB2BGR))
    assert ok
    return [
        (
            "nav_msgs/Odometry",
            "/robot/odom",
            at(0),
            {
                "header": header(at(0), "odom"),
                "child_frame_id": "base_link",
                "position": {"x": 1.25, "y": -2.5, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.38268343, "w": 0.92387953},
                "linear_velocity": {"x": 0.5, "y": 0.0, "z": 0.0},
                "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.1},
                "pose_covariance": [float(i) for i in range(36)],
                "twist_covariance": [None] + [0.0] * 35,
            },
        ),
        (
            "sensor_msgs/Image",
            "/camera/image",
            at(1),
            {
                "header": header(at(1), "camera"),
                "width": 4,
                "height": 3,
                "encoding": "rgb8",
                "format": "png",
                "data": base64.b64encode(png.tobytes()).decode(),
            },
        ),
        (
            "sensor_msgs/CompressedImage",
            "/camera/compressed",
            at(2),
            {
                "header": header(at(2), "camera"),
                "format": "jpeg",
                "data": base64.b64encode(b"\xff\xd8\xff not really a jpeg").decode(),
            },
        ),
        (
            "sensor_msgs/Imu",
            "/imu",
            at(3),
            {
                "header": header(at(3), "imu"),
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                "orientation_covariance": [0.01] * 9,
                "angular_velocity": {"x": 0.1, "y": 0.2, "z": 0.3},
                "angular_velocity_covariance": [0.02] * 9,
                "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 9.81},
                "linear_acceleration_covariance": [0.03] * 9,
            },
        ),
        ("std_msgs/String", "/chatter", at(4), {"data": "hello from the robot"}),
        ("geometry_msgs/Point", "/goal", at(5), {"x": 1.0, "y": 2.0, "z": 3.0}),
        ("acme_msgs/Gripper", "/gripper", at(6), {"force": 12.5, "closed": True}),
    ]


@pytest.fixture
def alice_records(alice, django_capture_on_commit_callbacks) -> list[Record]:
    """One upload of the samples, anchored in one tree (inline)."""
    envelopes = [
        alice.seal(
            seq,
            topic=topic,
            data_type=data_type,
            time=iso(moment),
            plaintext=fig4("alice", data_type, topic, moment, data),
        )
        for seq, (data_type, topic, moment, data) in enumerate(samples("alice"), start=1)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=alice.robot, envelopes=envelopes)
    for record in records:
        record.refresh_from_db()
    return records


def run_export(requester, django_capture_on_commit_callbacks, **selection) -> Export:
    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=requester, **selection)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    return export


def files_of(export: Export) -> tuple[bytes, bytes]:
    return export_files(export)


def decoded(mcap: bytes) -> dict[str, tuple]:
    """topic -> (schema name, message encoding, log time, publish time, decoded message)."""
    reader = make_reader(io.BytesIO(mcap), decoder_factories=[DecoderFactory()])
    found = {}
    for schema, channel, message in reader.iter_messages():
        value = None
        if channel.message_encoding == "cdr":
            value = DecoderFactory().decoder_for("cdr", schema)(message.data)
        else:
            value = json.loads(message.data)
        found[channel.topic] = (
            schema.name,
            channel.message_encoding,
            message.log_time,
            message.publish_time,
            value,
        )
    return found


def stamp_ns(moment: datetime) -> int:
    return int(moment.timestamp()) * 10**9 + moment.microsecond * 1000 + 789


def test_an_export_opens_with_independent_ros2_decoders_and_leaves_out_tampered_records(
    alice, alice_records, deployed, django_capture_on_commit_callbacks
):
    export = run_export(alice.owner, django_capture_on_commit_callbacks)
    assert (export.total, export.exported, export.excluded) == (7, 7, [])
    mcap, bundle = files_of(export)
    messages = decoded(mcap)

    schema, encoding, log_time, publish_time, odom = messages["/robot/odom"]
    assert (schema, encoding) == ("nav_msgs/msg/Odometry", "cdr")
    assert log_time == publish_time == stamp_ns(at(0))  # the capture stamp, to the nanosecond
    assert (odom.pose.pose.position.x, odom.pose.pose.position.y) == (1.25, -2.5)
    assert odom.pose.pose.orientation.w == pytest.approx(0.92387953)
    assert list(odom.pose.covariance) == [float(i) for i in range(36)]
    assert np.isnan(odom.twist.covariance[0])  # null is what the agent made of NaN
    assert odom.twist.twist.angular.z == 0.1
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "base_link")
    assert (odom.header.stamp.sec, odom.header.stamp.nanosec) == divmod(stamp_ns(at(0)), 10**9)

    schema, _, log_time, _, image = messages["/camera/image"]
    assert schema == "sensor_msgs/msg/Image"
    assert log_time == stamp_ns(at(1))
    assert (image.width, image.height, image.encoding, image.step) == (4, 3, "rgb8", 12)
    assert bytes(image.data) == PIXELS.tobytes()  # the pixels as the camera sent them

    _, _, _, _, compressed = messages["/camera/compressed"]
    assert (compressed.format, bytes(compressed.data)) == (
        "jpeg",
        b"\xff\xd8\xff not really a jpeg",
    )

    _, _, _, _, imu = messages["/imu"]
    assert imu.linear_acceleration.z == 9.81
    assert list(imu.orientation_covariance) == [0.01] * 9

    assert messages["/chatter"][0] == "std_msgs/msg/String"
    assert messages["/chatter"][4].data == "hello from the robot"
    assert messages["/chatter"][2] == int(at(4).timestamp()) * 10**9 + at(4).microsecond * 1000
    assert (messages["/goal"][4].x, messages["/goal"][4].z) == (1.0, 3.0)
    # A type rosbags does not know: its Fig. 4 record on a JSON channel.
    schema, encoding, _, _, gripper = messages["/gripper"]
    assert (schema, encoding) == ("acme_msgs/Gripper", "json")
    assert gripper["K"] == {"force": 12.5, "closed": True}

    report = verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    # The check left a verdict per record, as a view does: the audit trail shows the export.
    assert Verdict.objects.filter(access__viewer=alice.owner, outcome="verified").count() == 7

    # A record whose stored envelope changed is left out, and listed.
    bad = alice_records[1]
    tamper(bad)
    export = run_export(alice.owner, django_capture_on_commit_callbacks)
    assert (export.total, export.exported) == (7, 6)
    assert export.excluded == [
        {
            "record": str(bad.pk),
            "topic": "/camera/image",
            "captured_at": iso(at(1)),
            "reason": "integrity_check_failed",
            # an unsigned record's: no stream counts it
            "signer": None,
            "topic_seq": None,
        }
    ]
    mcap, bundle = files_of(export)
    assert "/camera/image" not in decoded(mcap)
    document = json.loads(bundle)
    assert str(bad.pk) not in {entry["record"] for entry in document["records"]}
    assert document["excluded"] == export.excluded
    assert verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap).ok
    page = session_client(alice.owner).get(reverse("export-detail", args=[export.pk]))
    assert page.status_code == 200
    assert f'data-record-id="{bad.pk}"' in page.content.decode()


def test_a_grantee_exports_only_what_they_may_view(
    alice, bob, alice_records, carol_robot, django_capture_on_commit_callbacks
):
    carol = carol_robot
    api = session_client(bob)
    # carol shares nothing with bob: her robot is not one he may select.
    refused = api.post(EXPORTS, {"robots": [str(carol.pk)]}, format="json")
    assert refused.status_code == 400
    assert refused.json()["error"] == "invalid_selection"
    assert not Export.objects.exists()

    with django_capture_on_commit_callbacks(execute=True):
        answer = api.post(EXPORTS, {"topics": ["/chatter"]}, format="json")
    assert answer.status_code == 202, answer.content
    export = Export.objects.get(pk=answer.json()["id"])
    assert export.status == Export.Status.DONE
    document = json.loads(files_of(export)[1])
    assert [entry["record"] for entry in document["records"]] == [str(alice_records[4].pk)]
    assert document["requested_by"] == "bob"

    # The files are bob's alone: alice (whose records they are) gets a 404, as would carol.
    status = api.get(f"{EXPORTS}{export.pk}/").json()
    assert (status["status"], status["percent"]) == ("done", 100)
    assert api.get(status["mcap_url"]).status_code == 200
    assert session_client(alice.owner).get(status["mcap_url"]).status_code == 404
    assert session_client(alice.owner).get(f"{EXPORTS}{export.pk}/").status_code == 404

    # A message delivered again after a worker died mid-run: the export runs again, whole.
    Export.objects.filter(pk=export.pk).update(status=Export.Status.RUNNING)
    assert export_run(export_id=export.pk).status == Export.Status.DONE
    assert api.get(status["mcap_url"]).status_code == 200

    # Expired: the download is refused, and the sweep removes the files.
    Export.objects.filter(pk=export.pk).update(expires_at=timezone.now() - timedelta(seconds=1))
    assert api.get(status["bundle_url"]).status_code == 410
    assert exports_sweep() == {"requeued": 0, "expired": 1, "withdrawn": 0}
    assert not envelope_storage().exists(export.mcap_name)
    assert Export.objects.get(pk=export.pk).status == Export.Status.EXPIRED

    # An export whose message was lost (the broker was down) is queued again by the sweep.
    lost = Export.objects.create(
        requester=bob,
        selection=RecordSelection(topics=("/chatter",)).as_json(),
        total=1,
        expires_at=timezone.now() + timedelta(hours=1),
    )
    Export.objects.filter(pk=lost.pk).update(created_at=timezone.now() - timedelta(hours=1))
    assert exports_sweep() == {"requeued": 1, "expired": 0, "withdrawn": 0}
    assert Export.objects.get(pk=lost.pk).status == Export.Status.DONE


@pytest.fixture
def carol_robot(db) -> Robot:
    """An owner who shares with nobody (no chain work), with a robot and an unanchored record."""
    key = sm4.generate_key()
    carol = owner_create(username="carol", password=TEST_PASSWORD, sm4_key=key)
    robot, _token = robot_create(owner=carol, name="carol-bot")
    record_create(robot=robot, data=seal_for(robot, key, seq=1, topic="/chatter"))
    return robot


BAD_SELECTIONS = [
    {"robots": ["not-a-uuid"]},
    {"robots": "all"},
    {"topics": [5]},
    {"topics": ["/nothing-here"]},
    {"since": "yesterday"},
    {"since": "2026-05-02T00:00:00Z", "until": "2026-05-01T00:00:00Z"},
    {"topics": ["/chatter"] * 101},
    {"robots": [str(uuid.uuid4())]},
]


def test_an_exports_access_log_line_names_the_credential_that_asked(
    alice, bob, alice_records, make_owner_token, django_capture_on_commit_callbacks
):
    """The export is one access-log line per record owner, naming the browser session or the
    token that asked for it (and its rebuild), never "not recorded"."""
    token, key = make_owner_token(bob, scopes=("read",))
    asked = {"session": session_client(bob), "token": token_client(key)}
    for credential, api in asked.items():
        with django_capture_on_commit_callbacks(execute=True):
            answer = api.post(EXPORTS, {"topics": ["/chatter"]}, format="json")
        assert answer.status_code == 202, answer.content
        export = Export.objects.get(pk=answer.json()["id"])
        assert export.status == Export.Status.DONE
        line = Access.objects.filter(kind=Access.Kind.EXPORT).latest("pk")
        assert (line.viewer, line.record_owner, line.credential) == (bob, alice.owner, credential)
        assert line.token_id == (token.pk if credential == "token" else None)
        with django_capture_on_commit_callbacks(execute=True):
            again = api.post(f"{EXPORTS}{export.pk}/rebuild/")
        assert again.status_code == 202, again.content
        rebuilt = Export.objects.get(pk=again.json()["id"])
        assert rebuilt.status == Export.Status.DONE
        line = Access.objects.filter(kind=Access.Kind.EXPORT).latest("pk")
        assert (line.credential, line.token_id) == (credential, token.pk if line.token else None)
    assert not Access.objects.filter(credential=Credential.UNKNOWN).exists()


def test_a_bad_selection_is_a_400_or_a_form_error_and_changes_nothing(carol_robot):
    api = session_client(carol_robot.owner)
    for body in BAD_SELECTIONS:
        answer = api.post(EXPORTS, body, format="json")
        assert answer.status_code == 400, (body, answer.content)
        assert answer.json()["error"] in ("invalid_request", "invalid_selection"), body
    page = api.post(reverse("exports"), {"since": "2026-05-02T00:00", "until": "2026-05-01T00:00"})
    assert page.status_code == 400
    assert "errorlist" in page.content.decode()
    page = api.post(reverse("exports"), {"since": "2030-01-01T00:00"})
    assert page.status_code == 400
    assert "no record you may view" in page.content.decode()
    assert not Export.objects.exists()


def test_a_paired_robots_export_carries_its_signatures_and_leaves_out_refused_ones(
    make_paired_robot, deployed, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("erin")
    plaintexts = [
        fig4("erin", "std_msgs/String", "/chatter", at(s), {"data": f"{s}"}) for s in (1, 2)
    ]
    envelopes = [
        setup.seal(
            seq, topic="/chatter", data_type="std_msgs/String", time=iso(at(seq)), plaintext=body
        )
        for seq, body in zip((1, 2), plaintexts, strict=True)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=envelopes)
    export = run_export(setup.owner, django_capture_on_commit_callbacks)
    mcap, bundle = files_of(export)
    entries = json.loads(bundle)["records"]
    assert [base64.b64decode(entry["plaintext"]) for entry in entries] == plaintexts
    assert {entry["signature"]["signer"] for entry in entries} == {setup.robot.key_hash}
    report = verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap, contract=deployed.address)
    assert report.ok, (report.problems, [r.problems for r in report.failed])
    assert len(report.genuine) == 2

    # The robot's key on record is no longer the signer's (a changed database): its records'
    # signatures no longer hold at the check, and they are left out, with why.
    Robot.objects.filter(pk=setup.robot.pk).update(public_key=sm2.generate_keypair()[1])
    export = run_export(setup.owner, django_capture_on_commit_callbacks, topics=["/chatter"])
    assert export.exported == 0
    assert [item["reason"] for item in export.excluded] == ["signature_refused"] * 2
