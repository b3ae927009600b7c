"""The robot page and the owner pages of issue 35 in Chromium, on a desktop (1280x900) and a
phone (390x844): the robots table's "last seen" leads to the robot page, whose status updates
itself from the status API; a record page's previous/next; the audit a minute a line; the
confirmation of a grant of everything; the alerts page's texts. Screenshots of each page go to
test-artifacts/e2e/.

The portal runs in pytest-django's live server with chain work and integrity checks run
inline (eager) on the session's anvil: these tests are about the pages, not the worker.
"""

from datetime import UTC, timedelta
from pathlib import Path

import pytest
from django.conf import settings
from django.utils import timezone
from playwright.sync_api import Browser, Page, expect

from accounts.models import Robot
from sharing.models import Record
from sharing.services.uploads import record_create
from tests.pages.conftest import image, odometry
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]


def _upload(setup: RobotSetup, seq: int, ago: float, **kwargs: object) -> Record:
    moment = timezone.now() - timedelta(seconds=ago)
    stamp = moment.astimezone(UTC).isoformat().replace("+00:00", "Z")
    record = record_create(robot=setup.robot, data=setup.seal(seq, time=stamp, **kwargs))
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    return record


def _fits(page: Page) -> None:
    fits = page.evaluate("document.scrollingElement.scrollWidth <= window.innerWidth")
    assert fits, page.url


def test_robot_page_and_owner_pages_on_a_desktop_and_a_phone(
    live_server, make_robot, make_owner, client, browser: Browser, artifacts: Path, monkeypatch
):
    monkeypatch.setattr("sharing.views.robot.LATEST_REFRESH_SECONDS", 2)
    alice = make_robot("alice")
    make_owner("bob")
    poses = [
        _upload(alice, seq, 40 - seq, plaintext=odometry("alice", seq * 0.5, -seq))
        for seq in range(1, 5)
    ]
    _upload(
        alice,
        5,
        30,
        plaintext=image("alice"),
        topic="/robot/complicatedImage",
        data_type="sensor_msgs/Image",
    )
    client.force_login(alice.owner.user)
    session = client.cookies[settings.SESSION_COOKIE_NAME].value
    base = live_server.url
    errors: list[str] = []
    newest = poses[-1].seq

    for name, viewport in (("desktop", (1280, 900)), ("phone", (390, 844))):
        context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
        context.add_cookies([{"name": settings.SESSION_COOKIE_NAME, "value": session, "url": base}])
        context.on("weberror", lambda error: errors.append(str(error.error)))
        page = context.new_page()

        # The robots table says when each robot was last seen, and leads to its page.
        Robot.objects.filter(pk=alice.robot.pk).update(last_upload_at=timezone.now())
        page.goto(f"{base}/robots/")
        seen = page.get_by_test_id("robot-last-seen")
        expect(seen).to_contain_text("last seen")
        _fits(page)
        page.screenshot(path=artifacts / f"robots-{name}.png", full_page=True)
        seen.get_by_role("link").click()
        page.wait_for_url(f"**/robots/{alice.robot.pk}/")

        # The robot page: rates, the latest verified pose and image, the plot's slot.
        expect(page.locator("h1")).to_have_text(alice.robot.name)
        odom = page.locator("[data-testid=topic-rate][data-topic='/robot/odom']")
        if name == "desktop":  # the phone's pass comes after a newer pose
            expect(odom.get_by_test_id("rate-hour")).to_contain_text("(4)")
        expect(page.get_by_test_id("latest-pose-link")).to_have_text(f"/robot/odom #{newest}")
        expect(page.get_by_test_id("latest-pose")).to_contain_text("verified")
        expect(page.get_by_test_id("latest-image-img")).to_be_visible()
        expect(page.get_by_test_id("robot-plot")).to_have_attribute("data-topic", "/robot/odom")
        _fits(page)
        page.screenshot(path=artifacts / f"robot-page-{name}.png", full_page=True)

        # The status updates by itself: the robot was last heard of 3 hours ago now.
        Robot.objects.filter(pk=alice.robot.pk).update(
            last_upload_at=timezone.now() - timedelta(hours=3)
        )
        expect(page.get_by_test_id("robot-last-seen")).to_have_text(
            "last seen 3 h ago", timeout=20_000
        )
        # And a newer pose, checked against the chain, replaces the one shown.
        newer = _upload(alice, 6 if name == "desktop" else 7, 1, plaintext=odometry("alice", 9, 9))
        expect(page.get_by_test_id("latest-pose-link")).to_have_text(
            f"/robot/odom #{newer.seq}", timeout=20_000
        )
        newest = newer.seq

        # A record page: previous and next of the same robot and topic, back to the list.
        page.goto(f"{base}/records/?topic=%2Frobot%2Fodom&sort=captured")
        page.get_by_test_id("open-record").first.click()
        page.wait_for_url(f"**/records/{poses[0].pk}/**")
        expect(page.get_by_test_id("record-no-previous")).to_be_visible()
        page.get_by_test_id("record-next").click()
        page.wait_for_url(f"**/records/{poses[1].pk}/**")
        expect(page.get_by_test_id("verdict")).to_have_attribute("data-verdict", "verified")
        _fits(page)
        page.screenshot(path=artifacts / f"record-nav-{name}.png", full_page=False)
        page.get_by_test_id("record-back").click()
        page.wait_for_url("**/records/?topic=%2Frobot%2Fodom&sort=captured&top=*")  # as it was

        # The audit: keys and grants first, then anchoring a minute a line.
        page.goto(f"{base}/audit/")
        expect(page.locator("#audit-anchoring [data-kind=upload]").first).to_contain_text("(UTC)")
        _fits(page)
        page.screenshot(path=artifacts / f"audit-{name}.png", full_page=True)

        # A grant of everything asks first.
        page.goto(f"{base}/grants/")
        page.fill("#id_grantee", "bob")
        expect(page.locator("#id_expires_at")).to_have_attribute("placeholder", "YYYY-MM-DD HH:MM")
        page.screenshot(path=artifacts / f"grants-{name}.png", full_page=True)
        page.click("#grant-submit")
        expect(page.get_by_test_id("grant-confirm-all")).to_contain_text("until you revoke it")
        _fits(page)
        page.screenshot(path=artifacts / f"grant-confirm-{name}.png", full_page=True)
        page.get_by_test_id("grant-confirm-cancel").click()
        page.wait_for_url("**/grants/#grant-form")

        page.goto(f"{base}/account/alerts/")
        _fits(page)
        page.screenshot(path=artifacts / f"alerts-{name}.png", full_page=True)
        context.close()

    assert not errors, errors
