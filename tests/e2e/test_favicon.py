"""The portal's icon: pages name it and it loads, so a browser asks for nothing that is not
there; pages that name none (the admin console's) get it at /favicon.ico."""

import pytest
from playwright.sync_api import Browser

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]


def test_pages_load_their_icon_and_ask_for_nothing_missing(live_server, browser: Browser):
    page = browser.new_page()
    failed: list[str] = []
    page.on("response", lambda answer: failed.append(answer.url) if answer.status >= 400 else None)
    page.on("requestfailed", lambda request: failed.append(request.url))
    for path in ("/login/", "/register/", "/admin/login/"):
        page.goto(f"{live_server.url}{path}")
        page.wait_for_load_state("networkidle")
    page.goto(f"{live_server.url}/login/")
    href = page.locator("link[rel=icon]").get_attribute("href")
    assert href.endswith("portal/favicon.svg")
    answer = page.request.get(f"{live_server.url}{href}")
    assert answer.status == 200
    assert answer.headers["content-type"].startswith("image/svg+xml")
    assert answer.body().startswith(b"<svg")
    # Asked for by name: redirected to the same file.
    answer = page.request.get(f"{live_server.url}/favicon.ico", max_redirects=0)
    assert answer.status == 301
    assert answer.headers["location"] == href
    assert failed == []
