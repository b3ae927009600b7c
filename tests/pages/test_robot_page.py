"""The robot page and its status API (issue 35): last seen, messages per second per topic, the
latest verified pose and image, the plot slot, who may see it; the robots table's "last seen".
"""

import re
import uuid
from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from accounts.lastseen import seen_ago_text
from accounts.models import Robot
from sharing.models import Access, Credential, Verdict
from sharing.robot_status import robot_activity
from sharing.services.grants import grant_create
from tests.pages.conftest import image, odometry
from tests.support.robot_setup import RobotSetup
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db


def _iso(moment: datetime) -> str:
    return moment.astimezone(UTC).isoformat().replace("+00:00", "Z")


@pytest.fixture
def alice(make_robot) -> RobotSetup:
    return make_robot("alice")


@pytest.fixture
def busy(alice, upload) -> RobotSetup:
    """alice's robot: 6 odometry messages in the last minute, 4 more in the last hour, 3 older;
    2 images in the last hour; nothing anchored (no chain work). Added a day ago."""
    now = timezone.now()
    Robot.objects.filter(pk=alice.robot.pk).update(created_at=now - timedelta(days=1))
    alice.robot.refresh_from_db()
    seq = 0
    for ago, count, topic, data_type in (
        (timedelta(seconds=20), 6, "/odom", "nav_msgs/Odometry"),
        (timedelta(minutes=30), 4, "/odom", "nav_msgs/Odometry"),
        (timedelta(hours=3), 3, "/odom", "nav_msgs/Odometry"),
        (timedelta(minutes=10), 2, "/camera", "sensor_msgs/Image"),
    ):
        for _ in range(count):
            seq += 1
            upload(alice, seq, anchor=False, topic=topic, data_type=data_type, time=_iso(now - ago))
    return alice


def test_rates_per_topic_over_the_last_minute_and_hour(busy):
    busy.robot.refresh_from_db()  # its last_upload_at, as a request reads it
    activity = robot_activity(busy.robot, now=timezone.now())
    rates = {rate.topic: rate for rate in activity.topics}
    assert set(rates) == {"/odom", "/camera"}
    assert (rates["/odom"].last_minute, rates["/odom"].last_hour) == (6, 10)
    assert (rates["/camera"].last_minute, rates["/camera"].last_hour) == (0, 2)
    assert rates["/odom"].per_second_minute == pytest.approx(0.1)
    assert [rate.topic for rate in activity.topics] == ["/odom", "/camera"]  # busiest first
    assert activity.last_upload_at is not None
    newest = max(record.captured_at for record in busy.robot.records.all())
    assert activity.last_captured_at == newest


def test_a_robot_added_within_the_hour_says_over_what_time_its_rate_is(client, alice, upload):
    """8 minutes old at a message every 10 s: 0.10/s over its 8 minutes, not 0.01/s over an
    hour it was not there for (issue 48)."""
    now = timezone.now()
    Robot.objects.filter(pk=alice.robot.pk).update(created_at=now - timedelta(minutes=8))
    for seq in range(1, 49):
        moment = now - timedelta(seconds=10 * (49 - seq))
        upload(alice, seq, anchor=False, time=_iso(moment))
    client.force_login(alice.owner.user)
    html = client.get(reverse("robot-detail", args=[alice.robot.pk])).content.decode()
    assert re.search(r'data-testid="rate-hour-heading">Last 8 min \(since it was added\)<', html)
    assert re.search(r'rate-hour">0.10/s <span class="help">\(48\)', html)
    api = client.get(reverse("api-v1:robot-status", args=[alice.robot.pk])).json()
    assert api["topics"][0]["hour_seconds"] == pytest.approx(480, abs=5)
    assert api["topics"][0]["per_second_hour"] == pytest.approx(0.1, abs=0.002)


def test_robot_page_shows_last_seen_and_rates(client, busy):
    Robot.objects.filter(pk=busy.robot.pk).update(
        last_upload_at=timezone.now() - timedelta(minutes=10)
    )
    client.force_login(busy.owner.user)
    page = client.get(reverse("robot-detail", args=[busy.robot.pk]))
    assert page.status_code == 200
    html = page.content.decode()
    assert re.search(r'data-testid="robot-last-seen"[^>]*>last seen 10 min ago<', html)
    rows = re.findall(
        r'data-topic="([^"]+)" data-testid="topic-rate">.*?rate-minute">([^<]+)<.*?'
        r'rate-hour">([^<]+)<',
        html,
        re.S,
    )
    assert rows == [("/odom", "0.10/s ", "0.00/s "), ("/camera", "0.00/s ", "0.00/s ")]
    assert "(6)" in html
    assert "(10)" in html
    # Nothing anchored: no verified pose or image is claimed.
    assert "No anchored odometry of this robot yet." in html
    assert "No anchored image of this robot yet." in html
    # The plot slot for the colleague's series plot, on the robot's odometry topic.
    slot = re.search(r"<div data-series-plot ([^>]*)>", html).group(1)
    assert f'data-robot="{busy.robot.pk}"' in slot
    assert 'data-topic="/odom"' in slot
    assert 'data-fields="position.x,position.y"' in slot
    assert 'data-refresh-seconds="5"' in slot
    # The path beside the time plot, over the window the heading names.
    assert 'data-mode="both"' in slot
    assert 'data-shape="path"' in slot
    assert "Trajectory, last 10 minutes" in html
    assert 'data-minutes="10"' in slot
    assert 'src="/static/portal/robot-page.js"' in html
    assert "<script>" not in html
    assert " onclick=" not in html


def test_latest_verified_pose_and_image_and_a_tampered_one(client, alice, upload):
    now = timezone.now()
    upload(alice, 1, plaintext=odometry("alice", 1.0, 1.0), time=_iso(now - timedelta(seconds=9)))
    upload(alice, 2, plaintext=odometry("alice", 3.25, -4.5), time=_iso(now - timedelta(seconds=5)))
    picture = upload(
        alice,
        3,
        topic="/robot/complicatedImage",
        data_type="sensor_msgs/Image",
        plaintext=image("alice"),
        time=_iso(now - timedelta(seconds=4)),
    )
    # Newer, but not anchored yet: not the one shown.
    upload(alice, 4, anchor=False, plaintext=odometry("alice", 9.0, 9.0), time=_iso(now))
    client.force_login(alice.owner.user)
    url = reverse("robot-detail", args=[alice.robot.pk])
    html = client.get(url).content.decode()
    pose = html.split('data-testid="latest-pose"')[1].split("</section>")[0]
    assert "verified" in pose
    assert "#2<" in pose
    assert "3.25" in pose
    assert "-4.5" in pose
    image_part = html.split('data-testid="latest-image"')[1].split("</section>")[0]
    assert 'src="data:image/png;base64,' in image_part
    # Both checked in one run: one access of the page, of two records, in the access log.
    viewed = Verdict.objects.filter(
        access__viewer=alice.owner, access__credential=Credential.SESSION
    )
    assert viewed.filter(outcome="verified").count() == 2
    (access,) = Access.objects.filter(viewer=alice.owner)
    assert (access.kind, access.count, access.credential) == ("page", 2, "session")

    tamper(picture)
    html = client.get(url).content.decode()
    image_part = html.split('data-testid="latest-image"')[1].split("</section>")[0]
    assert "TAMPERED, not shown" in image_part
    assert "data:image/png" not in image_part


def test_only_the_owner_sees_the_robot_page_and_status(
    client, alice, make_owner, make_owner_token, busy
):
    bob = make_owner("bob")
    grant_create(owner=alice.owner, grantee=bob, made_with="session")
    page_url = reverse("robot-detail", args=[alice.robot.pk])
    status_url = reverse("api-v1:robot-status", args=[alice.robot.pk])
    nowhere = reverse("api-v1:robot-status", args=[uuid.uuid4()])

    client.force_login(bob.user)
    assert client.get(page_url).status_code == 404
    assert client.get(reverse("robot-detail", args=[uuid.uuid4()])).status_code == 404
    theirs, none = client.get(status_url), client.get(nowhere)
    assert theirs.status_code == none.status_code == 404
    assert theirs.json() == none.json()
    client.logout()

    # Anonymous: sign in first.
    assert client.get(page_url).status_code == 302
    assert client.get(status_url).status_code in (401, 403)
    # The robot's own token reads no status of the owner's.
    robot = client.get(status_url, HTTP_AUTHORIZATION=f"Token {alice.token}")
    assert robot.status_code == 403
    # An owner API token: with `read`, yes; without it, no.
    _token, key = make_owner_token(alice.owner, scopes=("read",))
    answer = client.get(status_url, HTTP_AUTHORIZATION=f"Token {key}")
    assert answer.status_code == 200
    _token, share_only = make_owner_token(alice.owner, scopes=("share",))
    refused = client.get(status_url, HTTP_AUTHORIZATION=f"Token {share_only}")
    assert refused.status_code == 403
    assert refused.json()["error"] == "insufficient_scope"
    assert (
        client.get(
            reverse("api-v1:robot-status", args=["not-a-uuid"]), HTTP_AUTHORIZATION=f"Token {key}"
        ).status_code
        == 404
    )


def test_status_api_answers_last_seen_and_rates(client, busy):
    Robot.objects.filter(pk=busy.robot.pk).update(
        last_upload_at=timezone.now() - timedelta(minutes=10)
    )
    client.force_login(busy.owner.user)
    answer = client.get(reverse("api-v1:robot-status", args=[busy.robot.pk]))
    assert answer.status_code == 200
    assert answer["Cache-Control"] == "no-store, private"
    status = answer.json()
    assert status["robot"] == str(busy.robot.pk)
    assert status["last_seen"] == "10 min ago"
    assert status["last_seen_at"] is not None
    assert status["last_captured_at"] is not None
    odom, camera = status["topics"]
    assert (odom["topic"], odom["type"], odom["last_minute"], odom["last_hour"]) == (
        "/odom",
        "nav_msgs/Odometry",
        6,
        10,
    )
    assert odom["per_second_minute"] == pytest.approx(0.1)
    assert camera["topic"] == "/camera"
    assert camera["last_hour"] == 2
    # It checks nothing against the chain: no verdicts, no access-log entries.
    assert not Verdict.objects.exists()
    assert not Access.objects.exists()


def test_robots_table_shows_last_seen_and_links_the_robot_page(client, alice):
    Robot.objects.filter(pk=alice.robot.pk).update(
        last_upload_at=timezone.now() - timedelta(hours=3), last_seq=1795847771557316
    )
    client.force_login(alice.owner.user)
    html = client.get(reverse("robots")).content.decode()
    cell = html.split('data-testid="robot-last-seen"')[1].split("</td>")[0]
    assert "last seen 3 h ago" in cell
    assert reverse("robot-detail", args=[alice.robot.pk]) in cell
    assert "1795847771557316" not in html
    assert "Last seq" not in html


def test_never_seen_robot(client, alice):
    client.force_login(alice.owner.user)
    html = client.get(reverse("robots")).content.decode()
    assert "never seen" in html.split('data-testid="robot-last-seen"')[1].split("</td>")[0]
    page = client.get(reverse("robot-detail", args=[alice.robot.pk])).content.decode()
    assert "never seen" in page
    assert "Nothing captured in the last hour." in page


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (-5, "just now"),
        (0, "just now"),
        (2, "2 s ago"),
        (119, "119 s ago"),
        (600, "10 min ago"),
        (3 * 3600, "3 h ago"),
        (3 * 86400, "3 days ago"),
    ],
)
def test_seen_ago_wording(seconds, text):
    now = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
    assert seen_ago_text(now - timedelta(seconds=seconds), now=now) == text
    assert seen_ago_text(None, now=now) == "never"
