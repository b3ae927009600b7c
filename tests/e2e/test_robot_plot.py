"""The robot page's trajectory in Chromium, on a desktop (1280x900) and a phone (390x844): the
path drawn x against y (the same scale on both axes) beside the time plot, from one series
answer thinned along the path; legends above the plot areas, clear of the curves; beside each
other on a desktop, one above the other on a phone; refreshes that ask only for the newer
records and add them to the plot's one access line.

The portal runs in pytest-django's live server with chain work and integrity checks run
inline (eager) on the session's anvil: these tests are about the page, not the worker.
"""

import math
from datetime import UTC, timedelta
from pathlib import Path

import pytest
from django.conf import settings
from django.utils import timezone
from playwright.sync_api import Browser, Locator, expect

from sharing.models import Access, Record
from sharing.services.uploads import record_create_batch
from tests.pages.conftest import odometry
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

# Two minutes of a figure-8 at 10 Hz: more records than the page's 1000 points.
DRIVEN = 1200


def _drive(setup: RobotSetup, first: int, last: int) -> list[Record]:
    """Records first..last-1 of a figure-8 (6 m wide, 3 m high), at 10 Hz up to now."""
    start = timezone.now() - timedelta(seconds=DRIVEN / 10 + 5)
    made: list[Record] = []
    for at in range(first, last, 100):
        envelopes = []
        for i in range(at, min(at + 100, last)):
            a = 2 * math.pi * i / 600
            moment = (start + timedelta(seconds=i / 10)).astimezone(UTC)
            plaintext = odometry(
                setup.owner.username, 3 * math.sin(a), 3 * math.sin(a) * math.cos(a)
            )
            envelopes.append(
                setup.seal(
                    i + 1, plaintext=plaintext, time=moment.isoformat().replace("+00:00", "Z")
                )
            )
        made += record_create_batch(robot=setup.robot, envelopes=envelopes)
    return made


def _box(locator: Locator) -> dict[str, float]:
    box = locator.bounding_box()
    assert box is not None
    return box


def test_the_robot_page_draws_the_path_beside_the_time_plot_and_refreshes_only_new_records(
    live_server, make_robot, client, browser: Browser, artifacts: Path, monkeypatch
):
    # long enough that no refresh lands between a page's first answer and the checks of it
    monkeypatch.setattr("sharing.views.robot.PLOT_REFRESH_SECONDS", 8)
    alice = make_robot("alice")
    _drive(alice, 0, DRIVEN - 20)
    client.force_login(alice.owner.user)
    session = client.cookies[settings.SESSION_COOKIE_NAME].value
    base = live_server.url
    errors: list[str] = []
    driven = DRIVEN - 20

    for name, viewport in (("desktop", (1280, 900)), ("phone", (390, 844))):
        context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]})
        context.add_cookies([{"name": settings.SESSION_COOKIE_NAME, "value": session, "url": base}])
        context.on("weberror", lambda error: errors.append(str(error.error)))
        page = context.new_page()
        Access.objects.all().delete()
        page.goto(f"{base}/robots/{alice.robot.pk}/")
        plot = page.get_by_test_id("robot-plot")
        expect(plot).to_have_attribute("data-state", "ready", timeout=60_000)
        # One answer thinned along the path: 1000 points, each one checked record.
        expect(plot).to_have_attribute("data-method", "largest-triangle-three-buckets")
        expect(plot).to_have_attribute("data-points-shown", "1000")
        expect(plot).to_have_attribute("data-verified", str(driven))
        expect(plot.locator(".series-plot-status")).to_contain_text("points kept along the path")

        path_plot = plot.locator("svg[data-plot=path]")
        time_plot = plot.locator("svg[data-plot=time]")
        expect(path_plot).to_contain_text("position.x (m)")
        expect(path_plot).to_contain_text("position.y (m)")
        expect(time_plot).to_contain_text("capture time (UTC)")
        path_line = path_plot.locator(".series-plot-line")
        expect(path_line).to_have_attribute("data-points", "1000")
        assert time_plot.locator(".series-plot-line").count() == 2
        # The same scale on both axes: the figure-8 is drawn twice as wide as high.
        drawn = _box(path_line)
        assert 1.8 < drawn["width"] / drawn["height"] < 2.2, drawn
        # Legends above the plot areas, never over the curves.
        for svg in (path_plot, time_plot):
            area = _box(svg.locator(".series-plot-area"))
            entries = svg.locator(".series-plot-legend-entry")
            assert entries.count() == 2
            for index in range(entries.count()):
                entry = _box(entries.nth(index))
                assert entry["y"] + entry["height"] <= area["y"] + 1, (name, entry, area)
                assert area["x"] - 1 <= entry["x"]
                assert entry["x"] + entry["width"] <= area["x"] + area["width"] + 1
        # Beside each other on a desktop, one above the other on a phone; nothing overflows.
        left, right = _box(path_plot), _box(time_plot)
        if name == "desktop":
            assert left["x"] + left["width"] <= right["x"]
            assert abs(left["y"] - right["y"]) < 1
        else:
            assert left["y"] + left["height"] <= right["y"]
        assert right["x"] + right["width"] <= viewport[0]
        fits = page.evaluate("document.scrollingElement.scrollWidth <= window.innerWidth")
        assert fits
        plot.scroll_into_view_if_needed()
        page.screenshot(path=artifacts / f"robot-plot-{name}.png", full_page=True)

        # Newer records: a refresh asks for them alone and appends them; the access log
        # keeps the one line of this plot, its count grown by the newer records.
        (line,) = Access.objects.filter(viewer=alice.owner, kind=Access.Kind.PLOT)
        assert line.count == driven
        _drive(alice, driven, driven + 10)
        driven += 10
        expect(plot).to_have_attribute("data-verified", str(driven), timeout=30_000)
        (line,) = Access.objects.filter(viewer=alice.owner, kind=Access.Kind.PLOT)
        assert line.count == driven
        assert line.verdicts.count() == driven
        expect(plot.locator(".series-plot-status")).to_contain_text(
            "since, 10 newer records verified and added"
        )
        context.close()
    assert not errors, errors
