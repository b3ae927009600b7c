"""The robots page's install and pair commands in Chromium, at 1280x900 and on a 390x844 phone:
both commands are on screen whole (a long wheel name breaks the line, not the page).
Screenshots go to test-artifacts/e2e/install/.
"""

import pytest
from playwright.sync_api import Browser, expect

from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import ARTIFACTS

pytestmark = pytest.mark.django_db(transaction=True)

VIEWPORTS = {"desktop": {"width": 1280, "height": 900}, "phone": {"width": 390, "height": 844}}


def test_the_install_and_pair_commands_fit_a_desktop_and_a_phone(
    live_server, browser: Browser, make_owner
):
    owner = make_owner("alice")
    shots = ARTIFACTS / "install"
    shots.mkdir(parents=True, exist_ok=True)
    for name, viewport in VIEWPORTS.items():
        context = browser.new_context(viewport=viewport)
        page = context.new_page()
        page.goto(f"{live_server.url}/login/")
        page.fill("#id_username", owner.user.username)
        page.fill("#id_password", TEST_PASSWORD)
        page.click("#login-submit")
        expect(page.locator("[data-testid=signed-in-user]")).to_have_text(owner.user.username)
        page.goto(f"{live_server.url}/robots/")
        install = page.locator("[data-testid=install-command]")
        pair = page.locator("[data-testid=pair-command]")
        expect(install).to_contain_text("bin/pip install --no-deps ./authros_portal-")
        expect(pair).to_have_text(f"authros-agent pair --portal {live_server.url} --name NAME")
        page.screenshot(path=shots / f"robots-{name}.png", full_page=True)
        assert page.evaluate("document.documentElement.scrollWidth") <= viewport["width"], name
        for command in (install, pair):
            lines = command.evaluate("e => [...e.getClientRects()].map(r => [r.left, r.right])")
            assert min(left for left, _ in lines) >= 0, (name, lines)
            assert max(right for _, right in lines) <= viewport["width"], (name, lines)
        context.close()
