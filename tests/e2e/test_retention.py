"""Retention and deletion in Chromium, at 1280x900 and on a 390x844 phone: a robot's retention
set on the robots page, a record deleted after its confirmation page (then shown "deleted",
410), a selection deleted after its preview, and a robot unpaired only after its confirmation.

No worker stack: the portal runs in the live server thread with Celery eager on the session's
anvil, so records are anchored and checked inline.
"""

from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect

from accounts.models import Robot
from sharing.models import Record
from sharing.services.uploads import record_create
from tests.support.layout import cells_off_screen
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db(transaction=True)

DESKTOP = {"width": 1280, "height": 900}
PHONE = {"width": 390, "height": 844}


def signed_in(browser: Browser, base: str, username: str, viewport: dict) -> Page:
    page = browser.new_context(viewport=viewport).new_page()
    page.goto(f"{base}/login/")
    page.fill("#id_username", username)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")
    return page


def fully_shown(page: Page, selector: str) -> None:
    """The element is not clipped by the table's scrolling box (no hidden last column)."""
    box = page.locator(selector).bounding_box()
    wrap = page.locator(".table-wrap").first.bounding_box()
    assert box is not None
    assert wrap is not None
    assert box["x"] + box["width"] <= wrap["x"] + wrap["width"], selector


def no_sideways_scroll(page: Page) -> None:
    """The page itself fits the viewport (wide tables scroll inside their own box)."""
    width = page.evaluate("document.documentElement.scrollWidth")
    assert width <= page.viewport_size["width"], (page.url, width)


def every_cell_on_screen(page: Page, cells: str) -> None:
    """Each of the cells lies inside the viewport: a table shown as cards, not one to scroll
    sideways in its box."""
    outside = cells_off_screen(page, cells)
    assert page.locator(cells).count() > 0
    assert outside == 0, f"{outside} of {cells} outside the screen"


def test_retention_deletion_and_robot_removal_with_confirmation(
    live_server, browser: Browser, make_robot, artifacts: Path
):
    base = live_server.url
    alice = make_robot("alice")
    records = [record_create(robot=alice.robot, data=alice.seal(seq)) for seq in (1, 2, 3)]
    assert {r.status for r in Record.objects.all()} == {Record.Status.ANCHORED}
    robot_row = f"[data-testid=robot-row][data-robot-id='{alice.robot.id}']"

    # --- desktop: retention, then one record deleted after its confirmation page ------------
    page = signed_in(browser, base, "alice", DESKTOP)
    page.goto(f"{base}/robots/")
    row = page.locator(robot_row)
    row.locator("[data-testid=robot-retention-days]").fill("30")
    row.locator("[data-testid=robot-retention-save]").click()
    expect(page.locator("body")).to_contain_text("kept 30 days after capture")
    expect(page.locator(robot_row).locator("[data-testid=robot-retention-days]")).to_have_value(
        "30"
    )
    assert Robot.objects.get(pk=alice.robot.pk).retention_days == 30
    for control in ("robot-retention-save", "revoke-robot"):
        fully_shown(page, f"{robot_row} [data-testid={control}]")
    page.screenshot(path=artifacts / "retention-robots-desktop.png", full_page=True)

    page.goto(f"{base}/records/{records[0].id}/")
    expect(page.locator("[data-testid=verdict]")).to_have_attribute("data-verdict", "verified")
    page.click("[data-testid=record-delete-link]")
    expect(page.locator("h1")).to_have_text("Delete this record?")
    page.click("text=Cancel")  # changes nothing
    expect(page.locator("[data-testid=verdict]")).to_have_attribute("data-verdict", "verified")
    assert Record.objects.get(pk=records[0].pk).deleted_at is None
    page.click("[data-testid=record-delete-link]")
    with page.expect_navigation() as deleted:
        page.click("[data-testid=record-delete-confirm]")
    assert deleted.value.status == 410
    verdict = page.locator("[data-testid=verdict]")
    expect(verdict).to_have_attribute("data-verdict", "deleted")
    expect(verdict).to_contain_text("by alice")
    expect(page.locator("[data-testid=record-deleted-at]")).to_contain_text("by alice")
    expect(page.locator("#record-json")).to_have_count(0)
    record = Record.objects.get(pk=records[0].pk)
    assert record.deleted_at is not None
    assert record.purged_at is not None
    page.screenshot(path=artifacts / "retention-deleted-desktop.png", full_page=True)

    # --- phone: a selection deleted after its preview, a robot unpaired after confirming -----
    phone = signed_in(browser, base, "alice", PHONE)
    phone.goto(f"{base}/records/")
    phone.click("[data-testid=records-delete-link]")
    phone.select_option("#id_robot", str(alice.robot.id))
    phone.click("#records-delete-preview")
    expect(phone.locator("[data-testid=records-delete-count]")).to_have_text("2")
    no_sideways_scroll(phone)
    confirm = phone.locator("[data-testid=records-delete-confirm]")
    expect(confirm).to_be_in_viewport()
    confirm.click()
    expect(phone.locator("body")).to_contain_text("2 records deleted.")
    assert Record.objects.live().count() == 0

    phone.goto(f"{base}/robots/")
    no_sideways_scroll(phone)
    # A card per robot, its fields labelled, all on the screen: the retention form and the
    # revoke button need no sideways scrolling to be found.
    every_cell_on_screen(phone, "#robots-table td")
    label = phone.evaluate(
        "getComputedStyle(document.querySelector('#robots-table td'), '::before').content"
    )
    assert label == '"Name"'
    phone.screenshot(path=artifacts / "retention-robots-phone.png", full_page=True)
    phone.locator(robot_row).locator("[data-testid=revoke-robot]").click()
    expect(phone.locator("h1")).to_contain_text("Revoke the token of")
    no_sideways_scroll(phone)
    assert Robot.objects.get(pk=alice.robot.pk).is_active  # nothing yet
    phone.click("[data-testid=robot-revoke-confirm]")
    expect(phone.locator("body")).to_contain_text("is revoked")
    assert not Robot.objects.get(pk=alice.robot.pk).is_active
    phone.screenshot(path=artifacts / "retention-robot-revoked-phone.png", full_page=True)
