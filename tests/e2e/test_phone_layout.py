"""The pages on a phone (390x844) and a desktop (1280x900), in Chromium (issue 35): the
header's links fold under a Menu button and the list filters under a Filters button (both
with no script), a page of 25 records shows the first on the first screen as compact cards,
and no main page scrolls sideways or has anything blocked by the Content-Security-Policy.
Screenshots of every page at both sizes go to test-artifacts/e2e/layout/.

The portal runs in pytest-django's live server with chain work run inline (eager) on the
session's anvil: these tests are about the pages, not the worker.
"""

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from django.conf import settings
from playwright.sync_api import Browser, Page, expect

from sharing.grant_terms import grant_terms_make
from sharing.services.grants import grant_create
from sharing.services.uploads import record_create
from tests.pages.conftest import odometry

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
PHONE = (390, 844)
DESKTOP = (1280, 900)
PAGES = [
    "/dashboard/",
    "/records/",
    "/shared/",
    "/grants/",
    "/robots/",
    "/account/tokens/",
    "/exports/",
    "/audit/",
    "/access-log/",
    "/account/key/",
    "/account/password/",
    "/account/security/",
    "/account/alerts/",
    "/records/delete/",
    "/account/delete/",
]


@pytest.fixture
def shots(artifacts: Path) -> Path:
    """A folder of its own: each test's `artifacts` clears the screenshots of the last."""
    folder = artifacts / "layout"
    folder.mkdir(exist_ok=True)
    return folder


def _fits(page: Page) -> bool:
    return page.evaluate("document.documentElement.scrollWidth <= window.innerWidth")


@pytest.fixture
def signed_in(live_server, make_robot, client):
    """alice with 30 odometry records (two pages of 25) and bob's grant: the portal's
    address, her session, the path of her newest record."""
    alice = make_robot("alice")
    bob = make_robot("bob")
    for seq in range(1, 31):
        time = (NOON + timedelta(seconds=seq)).isoformat().replace("+00:00", "Z")
        record = record_create(
            robot=alice.robot,
            data=alice.seal(seq, time=time, plaintext=odometry("alice", seq, seq / 2)),
        )
    record_create(robot=bob.robot, data=bob.seal(1))
    grant_create(
        owner=bob.owner,
        grantee=alice.owner,
        made_with="session",
        terms=grant_terms_make(owner=bob.owner),
    )
    client.force_login(alice.owner.user)
    session = client.cookies[settings.SESSION_COOKIE_NAME].value
    # The newest record's page (with its plot) is a main page too.
    return live_server.url, session, f"/records/{record.pk}/"


def _page_at(browser: Browser, base: str, session: str, size: tuple[int, int]) -> Page:
    context = browser.new_context(viewport={"width": size[0], "height": size[1]})
    context.add_cookies([{"name": settings.SESSION_COOKIE_NAME, "value": session, "url": base}])
    # What the Content-Security-Policy blocks on these pages (none may be blocked).
    context.add_init_script(
        "window.__blocked = []; document.addEventListener('securitypolicyviolation',"
        " (e) => window.__blocked.push(e.effectiveDirective + ' ' + e.blockedURI));"
    )
    return context.new_page()


def test_every_main_page_fits_a_phone_and_a_desktop(signed_in, browser: Browser, shots: Path):
    base, session, record_page = signed_in
    errors: list[str] = []
    for name, size in (("desktop", DESKTOP), ("phone", PHONE)):
        page = _page_at(browser, base, session, size)
        page.on("pageerror", lambda error: errors.append(str(error)))
        for path in [*PAGES, record_page]:
            page.goto(base + path)
            page.wait_for_load_state("networkidle")  # the record page's plot draws itself
            assert _fits(page), (name, path)
            assert page.evaluate("window.__blocked") == [], (name, path)
            slug = path.strip("/").replace("/", "-")[:40]
            page.screenshot(path=shots / f"{slug}-{name}.png", full_page=True)
        page.context.close()
    assert errors == []


def test_the_header_menu_folds_on_a_phone_and_opens(signed_in, browser: Browser, shots: Path):
    base, session, _record_page = signed_in
    page = _page_at(browser, base, session, PHONE)
    page.goto(base + "/dashboard/")
    records_link = page.get_by_test_id("nav-records")
    expect(records_link).to_be_hidden()
    expect(page.get_by_test_id("logout")).to_be_hidden()
    header = page.locator(".site-header").bounding_box()
    assert header is not None
    assert header["height"] < 80  # one line: the name and the Menu button
    page.get_by_test_id("menu-button").click()
    expect(records_link).to_be_visible()
    expect(page.get_by_test_id("logout")).to_be_visible()
    assert _fits(page)
    page.screenshot(path=shots / "menu-open-phone.png")
    records_link.click()
    page.wait_for_url("**/records/")
    expect(page.get_by_test_id("nav-records")).to_be_hidden()  # closed again on the next page
    page.context.close()

    # On a desktop there is no button: the links are all there.
    page = _page_at(browser, base, session, DESKTOP)
    page.goto(base + "/dashboard/")
    expect(page.get_by_test_id("menu-button")).to_be_hidden()
    expect(page.get_by_test_id("nav-records")).to_be_visible()
    expect(page.get_by_test_id("logout")).to_be_visible()
    page.context.close()


def test_a_page_of_records_on_a_phone(signed_in, browser: Browser, shots: Path):
    base, session, _record_page = signed_in
    page = _page_at(browser, base, session, PHONE)
    page.goto(base + "/records/")
    rows = page.get_by_test_id("record-row")
    expect(rows).to_have_count(25)
    # The first record is on the first screen, whole, and within its width.
    first = rows.first.bounding_box()
    assert first is not None
    assert first["y"] + first["height"] <= PHONE[1]
    assert first["x"] >= 0
    assert first["x"] + first["width"] <= PHONE[0]
    # Compact cards: 25 of them in a few screens, not 7,500 px.
    tall = page.evaluate("document.documentElement.scrollHeight")
    assert _fits(page)
    page.screenshot(path=shots / "records-25-phone.png", full_page=True)
    assert tall < 3000, tall

    # The filters fold under their button, and open with it.
    robot = page.locator("#id_robot")
    expect(robot).to_be_hidden()
    page.get_by_test_id("filters-button").click()
    expect(robot).to_be_visible()
    assert _fits(page)
    page.screenshot(path=shots / "records-filters-open-phone.png")

    # A filter that does not hold opens them, with its error.
    page.goto(base + "/records/?status=lost")
    expect(page.locator("#id_status")).to_be_visible()
    expect(page.get_by_test_id("messages")).to_contain_text("Left out of the filters")
    expect(rows).to_have_count(25)
    page.context.close()

    # On a desktop the filters are shown, with no button.
    page = _page_at(browser, base, session, DESKTOP)
    page.goto(base + "/records/")
    expect(page.locator("#id_robot")).to_be_visible()
    expect(page.get_by_test_id("filters-button")).to_be_hidden()
    page.context.close()
