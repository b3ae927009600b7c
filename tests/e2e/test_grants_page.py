"""The grants page in Chromium, on a desktop (1280x900) and a phone (390x844): a grant limited
to a robot, a topic and a capture-time window, with an expiry; errors in words; the
confirmation before a revocation, cancelled and then confirmed.

The portal runs in pytest-django's live server with chain work run inline (eager) on
the session's anvil: this test is about the page, not the worker.
"""

from datetime import UTC, datetime, timedelta

import pytest
from playwright.sync_api import Browser, Page, expect

from sharing.models import Grant
from sharing.scope import scope_commitment
from sharing.services.grant_chain import grant_sync_on_chain
from tests.pages.conftest import upload  # noqa: F401  (the fixture)
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

DESKTOP = {"width": 1280, "height": 900}
PHONE = {"width": 390, "height": 844}


def sign_in(browser: Browser, base: str, username: str, viewport: dict) -> Page:
    page = browser.new_context(viewport=viewport).new_page()
    page.goto(f"{base}/login/")
    page.fill("#id_username", username)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")
    page.goto(f"{base}/grants/")
    return page


def fits_the_width(page: Page) -> bool:
    return page.evaluate("() => document.documentElement.scrollWidth <= window.innerWidth")


def test_scoped_grant_and_revoke_confirmation_on_desktop_and_phone(
    live_server,
    browser: Browser,
    make_robot,
    make_owner,
    upload,  # noqa: F811
    artifacts,
):
    alice = make_robot("alice")
    upload(alice, 1, topic="/robot/odom")
    upload(alice, 2, topic="/robot/camera")
    make_owner("bob")
    base = live_server.url
    page = sign_in(browser, base, "alice", DESKTOP)
    form = page.get_by_test_id("grant-form")

    # Errors read as sentences, and the form keeps what was typed.
    page.fill("#id_grantee", "nobody")
    page.click("#grant-submit")
    expect(form).to_contain_text("There is no owner with the username or address “nobody”")
    expect(page.locator("#id_grantee")).to_have_value("nobody")
    page.fill("#id_grantee", "bob")
    page.fill("#id_since", "2026-01-02T00:00")
    page.fill("#id_until", "2026-01-01T00:00")
    page.click("#grant-submit")
    expect(form).to_contain_text("“Captured before” must be later than “Captured from”.")
    page.screenshot(path=artifacts / "grants-desktop-errors.png", full_page=True)

    # A grant of one robot's /robot/odom records of 2026-01-01, expiring in a week.
    expires = (datetime.now(tz=UTC) + timedelta(days=7)).replace(second=0, microsecond=0)
    page.fill("#id_until", "2026-01-02T00:00")
    page.fill("#id_since", "2026-01-01T00:00")
    page.get_by_test_id("grant-robots").get_by_label(alice.robot.name).check()
    page.get_by_test_id("grant-topics").get_by_label("/robot/odom").check()
    page.fill("#id_expires_at", expires.strftime("%Y-%m-%dT%H:%M"))
    page.click("#grant-submit")
    row = page.locator("[data-testid=grant-given-row][data-grantee=bob]")
    expect(row).to_have_attribute("data-status", "active")
    expect(row.get_by_test_id("grant-scope")).to_contain_text(f"Robots: {alice.robot.name}.")
    expect(row.get_by_test_id("grant-scope")).to_contain_text("Topics: /robot/odom.")
    expect(row.get_by_test_id("grant-scope")).to_contain_text("from 2026-01-01 00:00")
    expect(row.get_by_test_id("grant-expiry")).to_contain_text(
        f"Until {expires:%Y-%m-%d %H:%M:%S} UTC"
    )
    grant = Grant.objects.get(grantee__user__username="bob")
    assert grant.scope_topics == ["/robot/odom"]
    assert grant.expires_at == expires
    assert scope_commitment(grant.scope) != b"\0" * 32
    page.screenshot(path=artifacts / "grants-desktop-scoped.png", full_page=True)

    # Revoke asks first; "Keep access" changes nothing.
    row.get_by_test_id("revoke-grant").click()
    confirm = page.get_by_test_id("revoke-confirm")
    expect(page.locator("h1")).to_have_text("Revoke bob's access?")
    expect(confirm).to_contain_text(f"Robots: {alice.robot.name}. Topics: /robot/odom.")
    page.screenshot(path=artifacts / "grants-desktop-revoke-confirm.png", full_page=True)
    page.get_by_test_id("revoke-cancel").click()
    expect(row).to_have_attribute("data-status", "active")

    # On a phone: the page fits the width, and the revocation is confirmed there.
    phone = sign_in(browser, base, "alice", PHONE)
    expect(phone.get_by_test_id("grant-form")).to_be_visible()
    assert fits_the_width(phone)
    phone.screenshot(path=artifacts / "grants-phone.png", full_page=True)
    phone_row = phone.locator("[data-testid=grant-given-row][data-grantee=bob]")
    # The grant is a card there: its terms and its buttons within the screen's width.
    expect(phone_row.get_by_test_id("grant-scope")).to_contain_text("Topics: /robot/odom.")
    revoke = phone_row.get_by_test_id("revoke-grant")
    box = revoke.bounding_box()
    assert box is not None
    assert box["x"] >= 0
    assert box["x"] + box["width"] <= PHONE["width"]
    revoke.click()
    button = phone.get_by_test_id("revoke-confirm-button")
    expect(button).to_be_in_viewport()
    assert fits_the_width(phone)
    phone.screenshot(path=artifacts / "grants-phone-revoke-confirm.png", full_page=True)
    button.click()
    expect(phone.get_by_test_id("messages")).to_contain_text("bob can no longer read your records")
    expect(phone_row).to_have_attribute("data-status", "revoked")
    # A revoked grant has nothing left to revoke or change.
    expect(phone_row.get_by_test_id("revoke-grant")).to_have_count(0)


def test_everything_asks_first_and_the_page_follows_the_chain_by_itself(
    live_server, browser: Browser, make_robot, make_owner
):
    """Nothing ticked asks for a confirmation on a page of its own (no grant before it); a
    grant pending on chain turns active on the open page without a reload (issue 35)."""
    alice = make_robot("alice")
    make_owner("bob")
    carol = make_owner("carol")
    base = live_server.url
    page = sign_in(browser, base, "alice", DESKTOP)

    page.fill("#id_grantee", "bob")
    page.click("#grant-submit")
    expect(page.locator("h1")).to_have_text("Share all your records with bob, with no end?")
    expect(page.get_by_test_id("grant-confirm-all")).to_contain_text("until you revoke it")
    assert not Grant.objects.exists()
    page.get_by_test_id("grant-confirm-all-button").click()
    bob_row = page.locator("[data-testid=grant-given-row][data-grantee=bob]")
    expect(bob_row).to_have_count(1)
    assert Grant.objects.get(grantee__user__username="bob").scope.is_all

    # A grant whose chain work has not run yet (its task not delivered): pending on the page.
    grant = Grant.objects.create(owner=alice.owner, grantee=carol)
    page.goto(f"{base}/grants/")
    carol_row = page.locator("[data-testid=grant-given-row][data-grantee=carol]")
    expect(carol_row).to_have_attribute("data-status", "pending")
    expect(page.get_by_test_id("grants-waiting")).to_be_visible()
    page.fill("#id_grantee", "typed, not sent")
    page.evaluate("() => { window.notReloaded = true; }")
    grant_sync_on_chain(grant_id=grant.pk)  # the worker's work, run here: the chain confirms it
    expect(carol_row).to_have_attribute("data-status", "active", timeout=20_000)
    expect(carol_row.get_by_test_id("grant-status")).to_have_text("active")
    assert page.evaluate("() => window.notReloaded") is True
    expect(page.locator("#id_grantee")).to_have_value("typed, not sent")
