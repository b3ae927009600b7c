"""The alerts page in Chromium, at 1280x900 and on a 390x844 phone: choose what is sent where,
see a mistake explained, add a webhook (its secret shown once), send a test alert and find it
in the delivery log, delete the webhook after confirming. No worker stack: tasks run inline
in the live server's thread."""

import re
from collections.abc import Iterator

import pytest
from django.core import mail
from playwright.sync_api import Browser, Page, expect

from accounts.services.owners import owner_create
from portal.celery import app as celery_app
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import ARTIFACTS, Screenshots

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture
def eager_retries() -> Iterator[None]:
    """Deliveries run inline and retry inline (Celery does so only without propagation)."""
    celery_app.conf.task_eager_propagates = False
    yield
    celery_app.conf.task_eager_propagates = True


def _sign_in(page: Page, base: str, username: str) -> None:
    page.goto(f"{base}/login/")
    page.fill("#id_username", username)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("button[type=submit]")
    expect(page.get_by_test_id("signed-in-user")).to_have_text(username)


def _fits_the_viewport(page: Page) -> bool:
    return page.evaluate(
        "document.documentElement.scrollWidth <= document.documentElement.clientWidth"
    )


def test_an_owner_sets_up_alerts_on_desktop_and_phone(
    deployed, live_server, browser: Browser, settings, eager_retries
):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    settings.ALERTS_WEBHOOK_PORTS = [9]  # the receivers below listen on port 9
    owner_create(username="dora", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    shots = Screenshots(ARTIFACTS / "alerts")
    shots.directory.mkdir(parents=True, exist_ok=True)
    base = live_server.url

    desktop = browser.new_context(viewport={"width": 1280, "height": 900})
    page = desktop.new_page()
    _sign_in(page, base, "dora")
    page.get_by_test_id("nav-alerts").click()
    expect(page.get_by_role("heading", name="Alerts", exact=True)).to_be_visible()
    # Silent robots by e-mail without saying after how long: explained, nothing saved.
    page.fill("#id_email", "dora@example.org")
    page.get_by_test_id("email-record_tampered").check()
    page.get_by_test_id("email-robot_silent").check()
    page.get_by_test_id("webhook-grant_revoked").check()
    page.click("#alert-preferences-submit")
    expect(page.locator(".errorlist")).to_contain_text("Say after how long a robot is silent")
    expect(page.get_by_test_id("email-robot_silent")).to_be_checked()  # the choice is kept
    page.fill("#id_robot_silent_minutes", "45")
    page.click("#alert-preferences-submit")
    expect(page.get_by_test_id("messages")).to_contain_text("We sent a link to dora@example.org")
    expect(page.get_by_test_id("email-state")).to_contain_text("not confirmed")
    # The owner opens the link the e-mail brought (Django's test mailbox).
    [confirmation] = mail.outbox
    page.goto(re.search(r"http://\S+/account/alerts/verify/\S+/", confirmation.body).group(0))
    expect(page.get_by_test_id("messages")).to_contain_text("dora@example.org is confirmed")
    expect(page.get_by_test_id("email-state")).to_contain_text("confirmed")
    expect(page.locator("#id_robot_silent_minutes")).to_have_value("45")
    expect(page.get_by_test_id("email-robot_silent")).to_be_checked()
    expect(page.get_by_test_id("email-gas_low")).not_to_be_checked()

    # A loopback receiver is refused without the setting (the page says why) ...
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    page.fill("#id_url", "http://127.0.0.1:9/hook")
    page.click("#webhook-create-submit")
    expect(page.locator("#webhook-create-form .errorlist")).to_contain_text("public addresses")
    # ... and taken with it; the secret is shown once.
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    settings.ALERTS_WEBHOOK_PORTS = [9]  # the receivers below listen on port 9
    page.fill("#id_url", "http://127.0.0.1:9/hook")
    page.click("#webhook-create-submit")
    secret = page.get_by_test_id("webhook-secret").inner_text()
    assert re.fullmatch(r"whsec_[A-Za-z0-9_-]{43}", secret)
    shots(page, "webhook-secret-desktop")
    page.get_by_role("link", name="Back to your alert settings").click()
    expect(page.get_by_test_id("webhook-endpoint")).to_contain_text("http://127.0.0.1:9/hook")
    assert secret not in page.content()

    # A test alert: the e-mail goes out (Django's test mailbox), the webhook cannot be reached
    # (nothing listens on port 9) and the log says so.
    page.get_by_test_id("alert-test").click()
    expect(page.get_by_test_id("messages")).to_contain_text("on its way to 2 channels.")
    expect(page.locator("[data-testid=alert-delivery][data-status=sent]")).to_contain_text(
        "dora@example.org"
    )
    expect(page.locator("[data-testid=alert-delivery][data-status=pending]")).to_have_count(0)
    assert mail.outbox[-1].subject == "[AuthROS] A test alert"
    assert len(mail.outbox) == 2
    assert _fits_the_viewport(page)
    shots(page, "alerts-desktop")
    desktop.close()

    phone = browser.new_context(viewport={"width": 390, "height": 844}, is_mobile=True)
    page = phone.new_page()
    _sign_in(page, base, "dora")
    page.goto(f"{base}/account/alerts/")
    checkbox = page.get_by_test_id("webhook-gas_low")
    checkbox.scroll_into_view_if_needed()
    expect(checkbox).to_be_in_viewport()
    checkbox.check()
    page.fill("#id_gas_low_below_ether", "0.02")
    page.click("#alert-preferences-submit")
    expect(page.get_by_test_id("messages")).to_contain_text("Your alert settings are saved")
    expect(page.get_by_test_id("webhook-gas_low")).to_be_checked()
    assert _fits_the_viewport(page)
    shots(page, "alerts-phone")
    page.once("dialog", lambda dialog: dialog.accept())
    page.get_by_test_id("webhook-delete").click()
    expect(page.get_by_test_id("messages")).to_contain_text("was deleted")
    expect(page.get_by_test_id("webhook-endpoint")).to_have_count(0)
    phone.close()
