"""The access log in Chromium, at 1280x900 and on a 390x844 phone, one line per access (a plot
of five records is one line): an owner filters the accesses to their data and downloads them as
CSV; a grantee reads their own views of shared data as
cards, every field inside the screen.

No worker, no anvil: the log only reads verdicts, made here straight in the database
(tests/support/access_log_data.py). Screenshots go to test-artifacts/e2e/access-log/.
"""

import csv
import io
from pathlib import Path

import pytest
from playwright.sync_api import Browser, BrowserContext, Page, expect

from sharing.models import Record
from tests.support.access_log_data import (
    CAROL_TOPIC,
    FORMULA_TOKEN,
    access_log_world,
    plot,
    stored_record,
)
from tests.support.layout import cells_off_screen
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import ARTIFACTS

pytestmark = pytest.mark.django_db(transaction=True)

PHONE = {"width": 390, "height": 844}


@pytest.fixture
def world(settings):
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]
    # Sign-ups awaiting approval: nothing of theirs goes to the chain, none is needed here.
    settings.SIGNUP_APPROVAL = True
    return access_log_world(signed_up=True)


def _signed_in(browser: Browser, base: str, username: str, viewport: dict) -> BrowserContext:
    context = browser.new_context(viewport=viewport, accept_downloads=True)
    page = context.new_page()
    page.goto(f"{base}/login/")
    page.fill("#id_username", username)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    expect(page.locator("[data-testid=signed-in-user]")).to_have_text(username)
    return context


def _nothing_overflows(page: Page) -> None:
    """No horizontal scrolling of the page, and every cell of the log inside the screen."""
    width = page.viewport_size["width"]
    assert page.evaluate("document.documentElement.scrollWidth") <= width
    assert cells_off_screen(page, "#access-log-table td") == 0


def _csv_of(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(Path(path).read_text(encoding="utf-8"))))


def _odometry(world, seq: int) -> Record:
    return stored_record(world.arm, seq, "/odom", "nav_msgs/Odometry")


def test_the_access_log_on_a_desktop_and_a_phone(live_server, browser: Browser, world):
    base = live_server.url
    shots = ARTIFACTS / "access-log"
    shots.mkdir(parents=True, exist_ok=True)

    # --- alice, desktop: every view of her data, filtered, and the CSV of the filtered set ----
    # Bob's plot of alice's odometry: one line naming its records, not one per record.
    plot(
        [world.records["odom"], *(_odometry(world, seq) for seq in range(2, 6))],
        world.bob,
        9,
    )
    desktop = _signed_in(browser, base, world.alice.username, {"width": 1280, "height": 900})
    page = desktop.pages[0]
    page.click("[data-testid=nav-access-log]")
    rows = page.locator("[data-testid=access-log-row]")
    # Others' views first: her own two are left out, said, and a click away (issue 48).
    expect(rows).to_have_count(4)
    expect(page.get_by_test_id("own-views-hidden")).to_contain_text("2 of your own views")
    page.get_by_test_id("show-own-views").click()
    expect(rows).to_have_count(6)
    expect(rows.first.locator("[data-testid=access-log-kind]")).to_have_text("plot, 5 records")
    expect(rows.first.locator("[data-testid=access-log-verdict]")).to_have_text("5 verified")
    expect(page.locator("#access-log-table thead")).to_be_visible()
    expect(page.locator("[data-testid=access-log-credential]")).to_contain_text(
        ["operator check in the admin", "browser session", "owner API token"]
    )
    _nothing_overflows(page)
    page.screenshot(path=shots / "01-desktop.png", full_page=True)
    page.fill("#id_viewer", world.bob.username)
    page.select_option("#id_credential", "session")
    page.select_option("#id_verdict", "tampered")  # not his plot's: every record verified
    page.click("#filter-submit")
    expect(rows).to_have_count(1)
    expect(rows.first.locator("[data-testid=access-log-verdict]")).to_have_text("TAMPERED")
    expect(page.locator("[data-testid=access-log-count]")).to_have_text(
        "1 access matches these filters."
    )
    with page.expect_download() as download:
        page.click("[data-testid=access-log-csv]")
    assert download.value.suggested_filename.startswith("access-log-incoming-")
    lines = _csv_of(download.value.path())
    assert [(row["viewer"], row["verdict"], row["credential"]) for row in lines] == [
        (world.bob.username, "tampered", "session")
    ]
    assert lines[0]["record"] == str(world.records["odom"].pk)
    desktop.close()

    # --- bob, phone: his own views of shared data, as compact rows ----------------------------
    phone = _signed_in(browser, base, world.bob.username, PHONE)
    page = phone.pages[0]
    page.goto(f"{base}/access-log/")
    expect(page.locator("[data-testid=access-log-none]")).to_be_visible()  # nobody viewed his
    page.click("[data-testid=access-log-tab-outgoing]")
    rows = page.locator("[data-testid=access-log-row]")
    expect(rows).to_have_count(4)
    # A compact row per access: the table head is hidden and no cell carries a label of its
    # own (each field in the same place of every row: when and who, what and its verdict, ...).
    head = page.evaluate("document.querySelector('#access-log-table thead').offsetHeight")
    assert head <= 1
    label = page.evaluate(
        """getComputedStyle(document.querySelector('#access-log-table td'), '::before')
            .content"""
    )
    assert label == "none"
    _nothing_overflows(page)
    expect(page.get_by_text(CAROL_TOPIC)).to_be_visible()
    expect(page.get_by_text("plot, 5 records")).to_be_visible()
    expect(page.get_by_text(f"owner API token “{FORMULA_TOKEN}”")).to_be_visible()
    page.screenshot(path=shots / "02-phone-outgoing.png", full_page=True)
    page.click("[data-testid=filters-button]")  # the filters fold on a phone
    page.fill("#id_owner", world.carol.username)
    page.click("#filter-submit")
    expect(rows).to_have_count(1)
    expect(rows.first.locator("[data-testid=access-log-owner]")).to_have_text(world.carol.username)
    _nothing_overflows(page)
    with page.expect_download() as download:
        page.click("[data-testid=access-log-csv]")
    assert download.value.suggested_filename.startswith("access-log-outgoing-")
    lines = _csv_of(download.value.path())
    assert [row["record_owner"] for row in lines] == [world.carol.username]
    page.screenshot(path=shots / "03-phone-filtered.png", full_page=True)
    phone.close()
