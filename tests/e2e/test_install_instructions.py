"""A new owner's first screen in Chromium, at 1280x900 and on a 390x844 phone (issue 48): the
dashboard leads to pairing a first robot in three steps (install, pair, approve), the pair
command naming this portal's own address; on the Robots page the install's pip text is folded
until asked for. Every command is on screen whole (a long wheel name breaks the line, not the
page). Screenshots go to test-artifacts/e2e/install/.
"""

import pytest
from playwright.sync_api import Browser, Locator, expect

from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import ARTIFACTS

pytestmark = pytest.mark.django_db(transaction=True)

VIEWPORTS = {"desktop": {"width": 1280, "height": 900}, "phone": {"width": 390, "height": 844}}


def _fits(command: Locator, width: int, name: str) -> None:
    lines = command.evaluate("e => [...e.getClientRects()].map(r => [r.left, r.right])")
    assert lines, name
    assert min(left for left, _ in lines) >= 0, (name, lines)
    assert max(right for _, right in lines) <= width, (name, lines)


def test_a_new_owners_first_screen_pairs_a_robot_at_this_portals_address(
    live_server, browser: Browser, make_owner
):
    owner = make_owner("alice")
    shots = ARTIFACTS / "install"
    shots.mkdir(parents=True, exist_ok=True)
    pair_text = f"~/authros-agent/bin/authros-agent pair --portal {live_server.url} --name"
    for name, viewport in VIEWPORTS.items():
        context = browser.new_context(viewport=viewport)
        page = context.new_page()
        page.goto(f"{live_server.url}/login/")
        page.fill("#id_username", owner.user.username)
        page.fill("#id_password", TEST_PASSWORD)
        page.click("#login-submit")
        expect(page.locator("[data-testid=signed-in-user]")).to_have_text(owner.user.username)

        # Signed in, the dashboard: its first screen is the first robot's three steps.
        page.goto(f"{live_server.url}/dashboard/")
        first = page.get_by_test_id("first-robot")
        expect(first.get_by_role("heading", level=2)).to_have_text("Pair your first robot")
        steps = first.locator("ol.first-steps > li h3")
        expect(steps).to_have_text(
            ["Install the agent on the robot", "Pair it with this portal", "Approve it here"]
        )
        assert first.evaluate("e => e.getBoundingClientRect().top") < viewport["height"], name
        install = first.get_by_test_id("install-command")
        pair = first.get_by_test_id("pair-command")
        expect(install).to_contain_text("--require-hashes -r requirements/agent.txt")
        expect(pair).to_have_text(f"{pair_text} my-robot")
        expect(first.get_by_label("Pairing code")).to_be_visible()
        expect(page.get_by_test_id("record-count")).to_have_count(0)
        page.screenshot(path=shots / f"dashboard-{name}.png", full_page=True)
        assert page.evaluate("document.documentElement.scrollWidth") <= viewport["width"], name
        for command in (install, pair):
            _fits(command, viewport["width"], name)

        # The Robots page: the pip text folded until asked for; the pair command shown.
        page.goto(f"{live_server.url}/robots/")
        install = page.get_by_test_id("install-command")
        pair = page.get_by_test_id("pair-command")
        expect(pair).to_have_text(f"{pair_text} NAME")
        expect(install).to_be_hidden()
        page.get_by_test_id("install-details").locator("summary").click()
        expect(install).to_contain_text("bin/pip install --no-deps ./authros_portal-")
        page.screenshot(path=shots / f"robots-{name}.png", full_page=True)
        assert page.evaluate("document.documentElement.scrollWidth") <= viewport["width"], name
        for command in (install, pair):
            _fits(command, viewport["width"], name)
        context.close()
