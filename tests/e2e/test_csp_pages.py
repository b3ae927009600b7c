"""The Content-Security-Policy in Chromium: the pages that run SM2 on the owner's key
(registration with a generated key, key rotation with a typed one), the everyday pages, the
API docs and the admin console run under it without a single violation; an injected inline script is
refused and reported.

Violations are collected from the `securitypolicyviolation` events of every page (listened
for before any of the page's own scripts run) and from the browser's requests to the report
endpoint.
"""

import uuid

import pytest
from django.contrib.auth import get_user_model
from playwright.sync_api import Browser, BrowserContext, Page, expect

from accounts.selectors import owner_by_username, owner_key_bytes, owner_key_current
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

LISTEN = """
window.__cspViolations = [];
document.addEventListener("securitypolicyviolation", (event) => {
  window.__cspViolations.push(
    `${event.effectiveDirective} blocked ${event.blockedURI} in ${event.sourceFile}`
  );
});
"""


class Watched:
    """A browser context whose pages' CSP violations, reports and script errors are kept."""

    def __init__(self, browser: Browser) -> None:
        self.context: BrowserContext = browser.new_context()
        self.context.add_init_script(LISTEN)
        self.reports: list[str] = []
        self.errors: list[str] = []
        self.violations: list[str] = []
        self.context.on(
            "request", lambda r: self.reports.append(r.url) if "/csp-report/" in r.url else None
        )
        self.context.on("weberror", lambda error: self.errors.append(str(error.error)))
        self.page = self.context.new_page()

    def visit(self, url: str) -> Page:
        self.collect()
        self.page.goto(url)
        return self.page

    def collect(self) -> None:
        """The violations of the page shown now (before it is left)."""
        if self.page.url.startswith("http"):
            self.violations += self.page.evaluate("window.__cspViolations || []")
            self.page.evaluate("window.__cspViolations = []")


def test_the_key_pages_and_the_admin_run_with_no_violation(live_server, deployed, browser: Browser):
    base = live_server.url
    watched = Watched(browser)
    name = f"csp-{uuid.uuid4().hex[:6]}"

    # Registration: the key generated in the browser, encrypted to the portal's SM2 key.
    page = watched.visit(f"{base}/register/")
    expect(page.locator("#register-submit")).to_be_enabled()
    page.fill("#id_username", name)
    page.fill("#id_password1", TEST_PASSWORD)
    page.fill("#id_password2", TEST_PASSWORD)
    page.click("#register-submit")
    page.wait_for_url("**/register/progress/")
    expect(page.locator("#registration-progress")).to_have_attribute("data-state", "confirmed")
    watched.collect()

    # Key rotation with a key the owner types.
    typed = uuid.uuid4().hex
    page = watched.visit(f"{base}/account/key/")
    expect(page.locator("#key-rotate-submit")).to_be_enabled()
    page.click("#type-own-key")
    page.fill("#id_sm4_key", typed)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#key-rotate-submit")
    expect(page.locator("#keys-table tbody tr")).to_have_count(2)
    owner = owner_by_username(name)
    assert owner_key_bytes(owner_key_current(owner)) == bytes.fromhex(typed)

    for path in ("/dashboard/", "/records/", "/grants/", "/account/alerts/", "/access-log/"):
        watched.visit(f"{base}{path}")
    # The API docs: Swagger UI's own bundle, and its set-up script from ?script.
    page = watched.visit(f"{base}/api/docs/")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("AuthROS portal API")

    # The admin console, with its own scripts (the changelist's actions and filters).
    get_user_model().objects.create_superuser("csp-admin", "", TEST_PASSWORD)
    page = watched.visit(f"{base}/admin/login/")
    page.fill("#id_username", "csp-admin")
    page.fill("#id_password", TEST_PASSWORD)
    page.click("input[type=submit]")
    page.wait_for_url(f"{base}/admin/")
    for path in ("/admin/auth/user/", "/admin/auth/user/add/", "/admin/accounts/owner/"):
        page = watched.visit(f"{base}{path}")
        expect(page.locator("#content")).to_be_visible()
    watched.collect()

    assert watched.violations == []
    assert watched.reports == []
    assert watched.errors == []

    # The policy holds: an inline script put into a page does not run, and is reported.
    with page.expect_request("**/csp-report/") as reported:
        page.evaluate(
            """() => {
              const script = document.createElement("script");
              script.textContent = "window.__ran = true";
              document.body.appendChild(script);
            }"""
        )
    assert page.evaluate("window.__ran === undefined")
    assert reported.value.response().status == 204
    watched.collect()
    assert [v for v in watched.violations if v.startswith("script-src-elem blocked inline")]
    watched.context.close()
