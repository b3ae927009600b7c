"""On a 390x844 phone each page's reason to be is on its first screen: the record's pose table
and its image, the grant form's submit, Export, Rotate the key; the access log's entries are
compact rows, not a card of every cell. Screenshots of each page at 1280x900 and 390x844 go to
test-artifacts/e2e/phone-first/."""

import pytest
from playwright.sync_api import Browser, Page

from sharing.services.uploads import record_create_batch
from tests.pages.conftest import image, odometry
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import ARTIFACTS

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

DESKTOP = {"width": 1280, "height": 900}
PHONE = {"width": 390, "height": 844}
SHOTS = ARTIFACTS / "phone-first"
# What is still seen of the element at the bottom of the first screen, at least.
SEEN = 40
# An access-log entry on a phone: four short lines (five where its records wrap), not a card
# of a labelled line per cell (about 430 px).
ROW_HEIGHT = 160


def _top(page: Page, selector: str) -> float:
    box = page.locator(selector).first.bounding_box()
    assert box is not None, selector
    return box["y"]


def test_each_pages_main_element_is_on_the_phones_first_screen(
    live_server, make_robot, browser: Browser
):
    alice = make_robot("alice")
    name = alice.owner.username
    envelopes = [
        alice.seal(1, plaintext=odometry(name, 1.5, -2.0)),
        alice.seal(
            2, topic="/robot/complicatedImage", data_type="sensor_msgs/Image",
            plaintext=image(name),
        ),
    ]  # fmt: skip
    pose, picture = record_create_batch(robot=alice.robot, envelopes=envelopes)  # anchored inline
    pages = {
        "record-pose": (f"/records/{pose.pk}/", "#odometry-table"),
        "record-image": (f"/records/{picture.pk}/", "#record-image"),
        "grants": ("/grants/", "#grant-submit"),
        "exports": ("/exports/", "#export-submit"),
        "key": ("/account/key/", "#key-rotate-submit"),
        "access-log": ("/access-log/?mine=on", '[data-testid="access-log-row"]'),
    }
    SHOTS.mkdir(parents=True, exist_ok=True)
    context = browser.new_context(viewport=PHONE)
    page = context.new_page()
    page.goto(f"{live_server.url}/login/")
    page.fill("#id_username", name)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")
    tops = {}
    for shown, (path, main) in pages.items():
        for size, viewport in (("desktop", DESKTOP), ("phone", PHONE)):
            page.set_viewport_size(viewport)
            page.goto(f"{live_server.url}{path}")
            page.locator(main).first.wait_for()
            page.screenshot(path=SHOTS / f"{shown}-{size}.png", full_page=True)
        page.screenshot(path=SHOTS / f"{shown}-phone-first-screen.png")
        tops[shown] = _top(page, main)
        width = page.evaluate("document.documentElement.scrollWidth")
        assert width <= PHONE["width"], (shown, width)
    assert all(top <= PHONE["height"] - SEEN for top in tops.values()), tops
    rows = page.locator('[data-testid="access-log-row"]')
    assert rows.count() >= 2
    heights = [rows.nth(i).bounding_box()["height"] for i in range(rows.count())]
    assert max(heights) <= ROW_HEIGHT, heights
    context.close()
