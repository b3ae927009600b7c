"""Every record counted, in Chromium (issue 44), on a desktop (1280x900) and a phone (390x844):
the record list names a missing gap as a warning, its link leads to the records around it, and
nothing overflows sideways, a long topic's name included; the robot page says the same of its
last hour, and its trajectory plot (the series' `streams`) of its range.

Records are uploaded as a paired robot sends them (signed, anchored inline on the session's
anvil); their `topic_seq` is then set on the rows, as the v2 ingest stores it: the pages read
rows. A record lost behind the portal's back is its row and stored envelope removed.
"""

from datetime import timedelta
from pathlib import Path

import pytest
from django.conf import settings
from django.utils import timezone
from playwright.sync_api import Browser, Page, expect

from sharing.models import Record
from sharing.services.uploads import record_create
from sharing.storage import envelope_storage
from tests.pages.conftest import odometry
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

# A long topic, as camera drivers name theirs: its gap's words must wrap, not widen the page.
LONG = "/robot/camera/front_left/image_rect_color/compressed_for_the_operator_console_stream"


def _stream(setup: RobotSetup, topic: str, count: int, *, first_seq: int) -> list[Record]:
    start = timezone.now() - timedelta(minutes=5)
    made = []
    for number in range(count):
        time = (start + timedelta(seconds=number)).isoformat().replace("+00:00", "Z")
        plaintext = odometry(setup.owner.username, float(number), float(number) / 2)
        data = setup.seal(first_seq + number, time=time, topic=topic, plaintext=plaintext)
        record = record_create(robot=setup.robot, data=data)
        Record.objects.filter(pk=record.pk).update(topic_seq=number)
        made.append(record)
    return made


def _lost(record: Record) -> None:
    envelope_storage().delete(record.storage_name)
    Record.objects.filter(pk=record.pk).delete()


def _no_horizontal_overflow(page: Page) -> None:
    fits = page.evaluate("document.scrollingElement.scrollWidth <= window.innerWidth")
    assert fits, page.url


def test_a_missing_gap_on_the_record_list_and_robot_page(
    live_server, make_paired_robot, client, browser: Browser, artifacts: Path
):
    alice = make_paired_robot("alice")
    odom = _stream(alice, "/robot/odom", 8, first_seq=1)
    long = _stream(alice, LONG, 3, first_seq=20)
    for record in odom[3:6]:
        _lost(record)
    _lost(long[1])
    client.force_login(alice.owner.user)
    session = client.cookies[settings.SESSION_COOKIE_NAME].value
    base = live_server.url
    errors: list[str] = []

    for name, viewport in (("desktop", (1280, 900)), ("phone", (390, 844))):
        context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
        context.add_cookies([{"name": settings.SESSION_COOKIE_NAME, "value": session, "url": base}])
        context.on("weberror", lambda error: errors.append(str(error.error)))
        page = context.new_page()

        page.goto(f"{base}/records/")
        warning = page.get_by_test_id("completeness-gaps")
        expect(warning).to_be_visible()
        expect(warning).to_have_attribute("role", "alert")
        expect(page.get_by_test_id("completeness-summary")).to_contain_text(
            "7 records, 4 missing, 2 gaps"
        )
        gaps = page.get_by_test_id("gap")
        expect(gaps).to_have_count(2)
        expect(gaps.nth(0)).to_contain_text(f"1 record missing on {LONG}")
        expect(gaps.nth(1)).to_contain_text("3 records missing on /robot/odom")
        expect(gaps.nth(1)).to_contain_text("between #3 and #5")
        for index in range(2):
            box = gaps.nth(index).bounding_box()
            assert box is not None
            assert box["x"] >= 0
            assert box["x"] + box["width"] <= viewport[0]
        _no_horizontal_overflow(page)
        page.screenshot(path=artifacts / f"completeness-records-{name}.png", full_page=True)

        # Its link: the records on either side of the gap, #2 and #6, their numbers shown.
        gaps.nth(1).get_by_test_id("gap-link").click()
        page.wait_for_url("**/records/?robot=*")
        rows = page.locator("tr.record-row")
        expect(rows).to_have_count(2)
        expect(page.get_by_test_id("record-topic-seq")).to_have_text(["topic #6", "topic #2"])
        expect(page.get_by_test_id("gap")).to_have_count(1)
        _no_horizontal_overflow(page)

        # The robot page: the same gaps in its last hour.
        page.goto(f"{base}/robots/{alice.robot.pk}/")
        section = page.get_by_test_id("robot-completeness")
        expect(section.get_by_test_id("completeness-summary")).to_contain_text(
            "Last hour: 7 records, 4 missing"
        )
        expect(section.get_by_test_id("gap")).to_have_count(2)
        # Its trajectory plot (the series API over the last 10 minutes) says so too.
        plot = page.get_by_test_id("robot-plot")
        expect(plot).to_have_attribute("data-state", "ready", timeout=30_000)
        expect(plot).to_have_attribute("data-missing", "3")
        expect(plot).to_have_attribute("data-verified", "5")
        expect(plot.locator(".series-plot-status")).to_contain_text(
            "3 records of the robot's count missing"
        )
        _no_horizontal_overflow(page)
        page.screenshot(path=artifacts / f"completeness-robot-{name}.png", full_page=True)
        context.close()
    assert not errors, errors
