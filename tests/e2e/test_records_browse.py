"""The record pages in Chromium, as people use them (issue 16), on a desktop (1280x900) and a
phone (390x844): a click anywhere on a row opens the record, nothing overflows, the page
numbers lead through the list, the odometry plot over a chosen range (drawn from the series
API) has its axes and a title that fits, and the
gallery shows the checked images of a range.

The portal runs in pytest-django's live server with chain work and integrity checks run
inline (eager) on the session's anvil: these tests are about the pages, not the worker.
"""

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from django.conf import settings
from playwright.sync_api import Browser, Page, expect

from sharing.models import Record
from sharing.services.uploads import record_create
from tests.pages.conftest import image, odometry
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
# A long topic, as camera drivers name theirs: it must wrap, not widen the table or the page.
CAMERA = "/robot/camera/front_left/image_rect_color/compressed_for_the_operator_console"


def _upload(setup: RobotSetup, seq: int, seconds: int, **kwargs: object) -> Record:
    time = (NOON + timedelta(seconds=seconds)).isoformat().replace("+00:00", "Z")
    record = record_create(robot=setup.robot, data=setup.seal(seq, time=time, **kwargs))
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    return record


def _no_horizontal_overflow(page: Page) -> None:
    fits = page.evaluate("document.scrollingElement.scrollWidth <= window.innerWidth")
    assert fits, page.url


def test_records_on_a_desktop_and_a_phone(
    live_server, make_robot, client, browser: Browser, artifacts: Path, monkeypatch
):
    monkeypatch.setattr("sharing.views.records.RECORDS_PER_PAGE", 3)
    alice = make_robot("alice")
    track = [
        _upload(alice, seq, 10 * seq, plaintext=odometry("alice", seq, seq / 2))
        for seq in range(1, 5)
    ]
    shots = [
        _upload(
            alice,
            seq,
            10 * seq,
            plaintext=image("alice"),
            topic=CAMERA,
            data_type="sensor_msgs/Image",
        )
        for seq in (5, 6)
    ]
    client.force_login(alice.owner.user)
    session = client.cookies[settings.SESSION_COOKIE_NAME].value
    base = live_server.url
    errors: list[str] = []

    for name, viewport in (("desktop", (1280, 900)), ("phone", (390, 844))):
        context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
        context.add_cookies([{"name": settings.SESSION_COOKIE_NAME, "value": session, "url": base}])
        context.on("weberror", lambda error: errors.append(str(error.error)))
        page = context.new_page()

        # The list: two pages of three, newest first, nothing clipped.
        page.goto(f"{base}/records/")
        rows = page.locator("tr.record-row")
        expect(rows).to_have_count(3)
        _no_horizontal_overflow(page)
        if name == "desktop":
            clipped = page.evaluate(
                "(() => { const w = document.querySelector('.table-wrap');"
                " return w.scrollWidth > w.clientWidth; })()"
            )
            assert not clipped
        else:
            # A compact card per record, every field in it shown, within the screen; the
            # upload counter marked "#" (tests/e2e/test_phone_layout.py: 25 of them).
            card = rows.first.bounding_box()
            assert card is not None
            assert card["x"] >= 0
            assert card["x"] + card["width"] <= 390
            for cell in rows.first.locator("td").all():
                expect(cell).to_be_visible()
            labels = rows.first.locator("td").evaluate_all(
                "cells => cells.map(c => getComputedStyle(c, '::before').content)"
            )
            assert '"#"' in labels
        expect(page.get_by_test_id("page-current")).to_have_text("1")
        page.screenshot(path=artifacts / f"records-{name}.png", full_page=True)
        page.get_by_test_id("page-last").click()
        expect(page.get_by_test_id("page-current")).to_have_text("2")
        expect(rows).to_have_count(3)
        expect(page.get_by_test_id("page-next")).to_have_count(0)
        page.get_by_test_id("page-first").click()
        expect(page.get_by_test_id("page-current")).to_have_text("1")

        # A click on the row (on its robot cell, away from the link's text) opens the record:
        # the first column's link covers the whole row.
        page.goto(f"{base}/records/?sort=captured")
        robot_cell = rows.first.locator('td[data-label="Robot"]')
        robot_cell.scroll_into_view_if_needed()
        cell = robot_cell.bounding_box()
        assert cell is not None
        page.mouse.click(cell["x"] + cell["width"] / 2, cell["y"] + cell["height"] / 2)
        # back: this list, as of its newest record
        page.wait_for_url(f"**/records/{track[0].pk}/?list=sort%3Dcaptured%26top%3D*")
        expect(page.get_by_test_id("verdict")).to_have_attribute("data-verdict", "verified")
        expect(page.get_by_test_id("upload-seq")).to_contain_text("1")

        # The plot over a chosen range (every record in it checked, from the series API),
        # with its axes in metres and a title that fits.
        page.fill("#plot-range [name=since]", "2026-03-01T12:00")
        page.fill("#plot-range [name=until]", "2026-03-01T12:01")
        page.click("#plot-submit")
        plot = page.get_by_test_id("trajectory-plot")
        expect(plot).to_have_attribute("data-state", "ready", timeout=30_000)
        expect(plot).to_have_attribute("data-verified", "4")
        expect(plot).to_have_attribute("data-refused", "0")
        expect(plot.locator(".series-plot-status")).to_contain_text(
            "4 records in range, 4 verified against the chain"
        )
        svg = plot.locator("svg")
        expect(svg).to_contain_text("position.x (m)")
        expect(svg).to_contain_text("position.y (m)")
        plot.scroll_into_view_if_needed()
        box = svg.bounding_box()
        title = plot.locator(".series-plot-title").bounding_box()
        assert box is not None
        assert title is not None
        assert box["x"] <= title["x"]
        assert title["x"] + title["width"] <= box["x"] + box["width"]
        assert box["x"] + box["width"] <= viewport[0]
        assert plot.locator(".series-plot-line").count() == 1
        # Each field over time, in an element added to the page later (the robot page's way).
        page.evaluate(
            """([robot]) => {
                const element = document.createElement("div");
                element.id = "speed-plot";
                Object.assign(element.dataset, {
                    seriesPlot: "", robot, topic: "/robot/odom", mode: "time",
                    fields: "linear_velocity.x,angular_velocity.z",
                    since: "2026-03-01T12:00:00Z", until: "2026-03-01T12:01:00Z",
                });
                document.querySelector("figure.plot").appendChild(element);
                window.AuthROSSeriesPlot.start(element);
            }""",
            [str(track[0].robot_id)],
        )
        speed = page.locator("#speed-plot")
        expect(speed).to_have_attribute("data-state", "ready", timeout=30_000)
        expect(speed.locator("svg")).to_contain_text("capture time (UTC)")
        assert speed.locator(".series-plot-line").count() == 2
        _no_horizontal_overflow(page)
        page.screenshot(path=artifacts / f"plot-{name}.png", full_page=True)

        # The gallery of the images around an image record, each checked, then shown.
        page.goto(f"{base}/records/{shots[0].pk}/")
        page.get_by_test_id("gallery-link").click()
        expect(page.get_by_test_id("gallery-image")).to_have_count(2)
        page.wait_for_function(
            "() => [...document.querySelectorAll('[data-testid=gallery-image]')]"
            ".every(i => i.complete && i.naturalWidth > 0)"
        )
        _no_horizontal_overflow(page)
        page.screenshot(path=artifacts / f"gallery-{name}.png", full_page=True)
        context.close()
    assert not errors, errors
