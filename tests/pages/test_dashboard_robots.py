"""The dashboard, and robots: a token shown once, the agent config, revocation."""

import os
import re

import pytest
import yaml
from django.test import Client
from django.urls import reverse

from accounts.models import DEFAULT_TOPICS, Robot
from accounts.selectors import owner_balance_wei, owner_key_current, robot_by_token
from chainworker.errors import ChainError
from chainworker.services import chain_client
from ros_agent.config import config_from_mapping
from sharing.models import Grant
from sharing.services.grants import grant_create, grant_revoke
from stack.anvil import free_port

pytestmark = pytest.mark.django_db


def test_dashboard_shows_identity_and_counts(
    client, make_robot, make_owner, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    bob = make_owner("bob")
    upload(alice, 1)
    upload(alice, 2)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    client.force_login(alice.owner.user)
    page = client.get(reverse("dashboard"))
    html = page.content.decode()
    assert page.status_code == 200
    owner = alice.owner
    assert owner.eoa_address in html
    assert owner.register_tx in html
    assert owner.fund_tx in html
    assert owner_key_current(owner).key_id in html
    assert re.search(r'data-testid="eoa-balance">\d+\.\d{6} ETH<', html)
    assert re.search(r'data-testid="record-count">2<', html)
    assert re.search(r'data-testid="grants-given-count">1<', html)
    assert re.search(r'data-testid="grants-received-count">0<', html)
    assert alice.key.hex() not in html

    assert 'data-testid="first-robot"' not in html

    # bob has no robot: his first step is pairing one; what is shared with him still shows.
    client.force_login(bob.user)
    html = client.get(reverse("dashboard")).content.decode()
    assert 'data-testid="first-robot"' in html
    assert 'data-testid="record-count"' not in html
    assert re.search(r'data-testid="grants-received-count">1<', html)


def test_a_new_owners_dashboard_pairs_a_first_robot_at_this_portals_address(
    client, pending_owner, settings
):
    settings.ALLOWED_HOSTS = [*settings.ALLOWED_HOSTS, "portal.example.org"]
    owner = pending_owner("newbie")
    client.force_login(owner.user)
    html = client.get(reverse("dashboard"), HTTP_HOST="portal.example.org:8443").content.decode()
    steps = re.findall(r'data-testid="first-step-(\w+)"', html)
    assert steps == ["install", "pair", "approve"]
    # The README's locked-set install, in a venv of its own.
    assert "python3 -m venv --system-site-packages ~/authros-agent" in html
    assert "~/authros-agent/bin/pip install --require-hashes -r requirements/agent.txt" in html
    pair = re.search(r'data-testid="pair-command">([^<]+)<', html).group(1)
    assert pair == (
        "~/authros-agent/bin/authros-agent pair --portal http://portal.example.org:8443 "
        "--name my-robot"
    )
    assert f'action="{reverse("robot-pair")}"' in html
    assert 'data-testid="record-count"' not in html

    # Once a robot exists (even unpaired since), the normal dashboard shows.
    client.post(reverse("robots"), {"name": "turtle-1", "topics": "/odom nav_msgs/Odometry"})
    Robot.objects.filter(owner=owner).update(is_active=False)
    html = client.get(reverse("dashboard")).content.decode()
    assert 'data-testid="first-robot"' not in html
    assert re.search(r'data-testid="robot-count">0<', html)


def test_dashboard_counts_agree_on_both_sides_of_a_revoked_grant(
    client, make_owner, django_capture_on_commit_callbacks
):
    alice, bob = make_owner("alice"), make_owner("bob")

    def counts(owner: object) -> tuple[str, str]:
        client.force_login(owner.user)
        html = client.get(reverse("dashboard")).content.decode()
        given = re.search(r'data-testid="grants-given-count">(\d+)<', html).group(1)
        received = re.search(r'data-testid="grants-received-count">(\d+)<', html).group(1)
        return given, received

    # Granted, the chain call not yet made: both sides count it.
    with django_capture_on_commit_callbacks() as chain_work:
        grant = grant_create(owner=alice, grantee=bob)
    assert grant.status == Grant.Status.PENDING
    assert counts(alice) == ("1", "0")
    assert counts(bob) == ("0", "1")
    for callback in chain_work:
        callback()
    grant.refresh_from_db()
    assert grant.status == Grant.Status.ACTIVE
    assert counts(alice) == ("1", "0")
    assert counts(bob) == ("0", "1")

    # Revoked, the chain call still pending: neither side counts it any more.
    grant = grant_revoke(owner=alice, grantee=bob)
    assert grant.status == Grant.Status.REVOKING
    assert counts(alice) == ("0", "0")
    assert counts(bob) == ("0", "0")
    assert "still being written on chain" in client.get(reverse("dashboard")).content.decode()


def test_dashboard_without_the_chain(client, pending_owner, settings):
    owner = pending_owner()
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    client.force_login(owner.user)
    page = client.get(reverse("dashboard"))
    html = page.content.decode()
    assert page.status_code == 200
    assert "not reachable right now" in html
    assert "unavailable" in html
    assert owner.eoa_address in html
    assert "still being registered" in html


def test_owner_balance_is_read_from_the_chain_and_its_failure_let_through(
    make_owner, pending_owner, settings
):
    owner = make_owner("olga")
    assert owner_balance_wei(owner) == chain_client().balance(owner.eoa_address) > 0
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(ChainError):
        owner_balance_wei(pending_owner())


# --- robots -------------------------------------------------------------------------------


def test_add_a_robot_shows_its_token_once(client, pending_owner, tmp_path):
    owner = pending_owner("hal")
    client.force_login(owner.user)
    assert client.get(reverse("robots")).status_code == 200
    page = client.post(
        reverse("robots"),
        {
            "name": "turtle-1",
            "topics": "/robot/odom nav_msgs/Odometry\n/scan sensor_msgs/LaserScan",
        },
    )
    assert page.status_code == 201
    assert "no-store" in page["Cache-Control"]
    html = page.content.decode()
    token = re.search(r'id="robot-token" data-testid="robot-token">([^<]+)<', html).group(1)
    robot = Robot.objects.get(owner=owner, name="turtle-1")
    assert robot_by_token(token) == robot
    assert str(robot.id) in html
    assert "shown only this once" in html

    config_text = re.search(r'<pre class="config"[^>]*>(.*?)</pre>', html, re.S).group(1)
    config_text = config_text.replace("&#x27;", "'").replace("&quot;", '"').replace("&amp;", "&")
    data = yaml.safe_load(config_text)
    assert data["token"] == token
    assert data["robot"] == str(robot.id)
    assert data["owner"] == "hal"
    assert data["portal_url"] == "http://testserver"
    assert data["topics"] == [
        {"name": "/robot/odom", "type": "nav_msgs/Odometry"},
        {"name": "/scan", "type": "sensor_msgs/LaserScan"},
    ]
    key_file = tmp_path / data["key_file"]
    key_file.write_text("00112233445566778899aabbccddeeff\n")
    os.chmod(key_file, 0o600)
    config = config_from_mapping(data, source="agent.yaml", base_dir=tmp_path)
    assert config.records_url == "http://testserver/api/v1/records/"
    assert "download-config" in html
    assert 'download="agent-turtle-1.yaml"' in html
    assert "00112233445566778899aabbccddeeff" not in html

    listing = client.get(reverse("robots")).content.decode()
    assert "turtle-1" in listing
    assert token not in listing
    assert robot.token_prefix in listing


def test_the_robots_page_folds_the_install_away_and_says_times_in_utc(client, pending_owner):
    owner = pending_owner("hal")
    client.force_login(owner.user)
    client.post(reverse("robots"), {"name": "turtle-1", "topics": "/odom nav_msgs/Odometry"})
    robot = Robot.objects.get(owner=owner)
    html = client.get(reverse("robots")).content.decode()
    details = re.search(r'<details class="install"[^>]*>(.*?)</details>', html, re.S).group(1)
    assert "--require-hashes -r requirements/agent.txt" in details
    # The pair command stays on screen, outside the fold.
    assert 'data-testid="pair-command"' in html
    assert 'data-testid="pair-command"' not in details
    assert '<span class="topic-type">nav_msgs/Odometry</span>' in html
    assert f"{robot.created_at:%Y-%m-%d %H:%M:%S} UTC" in html


def test_agent_config_download_names_a_token_file(client, pending_owner, tmp_path):
    owner = pending_owner("ida")
    client.force_login(owner.user)
    client.post(reverse("robots"), {"name": "r2", "topics": "/robot/odom nav_msgs/Odometry"})
    robot = Robot.objects.get(owner=owner)
    page = client.get(reverse("robot-config", args=[robot.id]))
    assert page.status_code == 200
    assert page["Content-Disposition"] == 'attachment; filename="agent-r2.yaml"'
    data = yaml.safe_load(page.content)
    assert data["token_file"] == "robot.token"
    assert "token" not in data
    (tmp_path / "robot.token").write_text("secret-token")
    (tmp_path / data["key_file"]).write_text("00112233445566778899aabbccddeeff")
    for name in ("robot.token", data["key_file"]):
        os.chmod(tmp_path / name, 0o600)
    assert config_from_mapping(data, source="agent.yaml", base_dir=tmp_path).robot == str(robot.id)


@pytest.mark.parametrize(
    ("form", "message"),
    [
        ({"name": "", "topics": "/a std_msgs/String"}, "This field is required"),
        ({"name": "r", "topics": ""}, "This field is required"),
        ({"name": "r", "topics": "/robot/odom"}, "write the topic name and its type"),
        ({"name": "r", "topics": "/robot/odom Odometry"}, "must be package/Message"),
        ({"name": "taken", "topics": "/a std_msgs/String"}, "already has a robot named"),
    ],
)
def test_add_robot_refusals_change_nothing(client, pending_owner, form, message):
    owner = pending_owner()
    client.force_login(owner.user)
    client.post(reverse("robots"), {"name": "taken", "topics": "/a std_msgs/String"})
    page = client.post(reverse("robots"), form)
    assert page.status_code == 400
    assert message in page.content.decode()
    assert Robot.objects.filter(owner=owner).count() == 1


def test_config_downloaded_again_has_the_topics_given_when_the_robot_was_added(
    client, pending_owner
):
    owner = pending_owner("ida")
    client.force_login(owner.user)
    topics = "/scan sensor_msgs/LaserScan\n/front_camera/image_raw sensor_msgs/Image"
    created = client.post(reverse("robots"), {"name": "lidar-1", "topics": topics})
    assert created.status_code == 201
    robot = Robot.objects.get(owner=owner)
    expected = [
        {"name": "/scan", "type": "sensor_msgs/LaserScan"},
        {"name": "/front_camera/image_raw", "type": "sensor_msgs/Image"},
    ]
    assert robot.topics == expected
    for _ in range(2):
        again = yaml.safe_load(client.get(reverse("robot-config", args=[robot.id])).content)
        assert again["topics"] == expected

    listing = client.get(reverse("robots")).content.decode()
    cell = re.search(r'data-testid="robot-topics">(.*?)</td>', listing, re.S).group(1)
    assert '<code>/scan</code> <span class="topic-type">sensor_msgs/LaserScan</span>' in cell
    assert (
        '<code>/front_camera/image_raw</code> <span class="topic-type">sensor_msgs/Image</span>'
        in cell
    )
    assert DEFAULT_TOPICS[0].name not in cell


def test_revoke_a_robot_token(client, pending_owner):
    owner = pending_owner()
    client.force_login(owner.user)
    client.post(reverse("robots"), {"name": "r1", "topics": "/a std_msgs/String"})
    robot = Robot.objects.get(owner=owner)
    url = reverse("robot-revoke", args=[robot.id])
    # GET is the confirmation: it says what happens, and changes nothing.
    confirm = client.get(url)
    assert confirm.status_code == 200
    assert "stops working at once" in confirm.content.decode()
    robot.refresh_from_db()
    assert robot.is_active
    page = client.post(url, follow=True)
    assert "is revoked" in page.content.decode()
    robot.refresh_from_db()
    assert not robot.is_active
    assert robot.revoked_at is not None


def test_revoking_an_already_revoked_token_changes_nothing(client, pending_owner):
    owner = pending_owner()
    client.force_login(owner.user)
    client.post(reverse("robots"), {"name": "r1", "topics": "/a std_msgs/String"})
    robot = Robot.objects.get(owner=owner)
    url = reverse("robot-revoke", args=[robot.id])
    assert "is revoked" in client.post(url, follow=True).content.decode()
    robot.refresh_from_db()
    revoked_at = robot.revoked_at
    page = client.post(url, follow=True)
    assert page.status_code == 200
    html = page.content.decode()
    assert "The token of r1 was already revoked" in html
    assert "is revoked: its uploads now fail" not in html
    robot.refresh_from_db()
    assert not robot.is_active
    assert robot.revoked_at == revoked_at


def test_robots_of_another_owner_are_out_of_reach(client, pending_owner):
    mallory = pending_owner("mallory")
    victim = pending_owner("victim")
    client.force_login(victim.user)
    # A name no random token on the page can contain by chance (a CSRF token once held "r1").
    client.post(reverse("robots"), {"name": "victims-turtlebot", "topics": "/a std_msgs/String"})
    robot = Robot.objects.get(owner=victim)
    client.force_login(mallory.user)
    assert client.post(reverse("robot-revoke", args=[robot.id])).status_code == 404
    assert client.get(reverse("robot-config", args=[robot.id])).status_code == 404
    page = client.get(reverse("robots")).content.decode()
    assert "victims-turtlebot" not in page
    assert str(robot.id) not in page
    robot.refresh_from_db()
    assert robot.is_active


def test_robot_forms_need_csrf(pending_owner):
    owner = pending_owner()
    client = Client(enforce_csrf_checks=True)
    client.force_login(owner.user)
    page = client.post(reverse("robots"), {"name": "r1", "topics": "/a std_msgs/String"})
    assert page.status_code == 403
    assert "security token (CSRF)" in page.content.decode()
    assert not Robot.objects.exists()
    # With the token from the page, the same form goes through.
    form_page = client.get(reverse("robots"))
    token = form_page.cookies["csrftoken"].value
    page = client.post(
        reverse("robots"),
        {"name": "r1", "topics": "/a std_msgs/String", "csrfmiddlewaretoken": token},
    )
    assert page.status_code == 201
