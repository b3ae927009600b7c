"""F9 in Chromium: the register page generates the owner's key in the browser
(crypto.getRandomValues), so an owner registers without typing one; it is offered as a key
file, two registrations get two different keys, and a typed key that is a word is refused.

The portal runs in pytest-django's live server with chain work run inline (eager) on
the session's anvil: these tests are about the page, not the worker.
"""

import re
import uuid
from pathlib import Path

import pytest
from playwright.sync_api import Browser, Page, expect

from accounts.models import Owner
from accounts.selectors import owner_by_username, owner_key_bytes, owner_key_current
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]


def fill_in(page: Page, base_url: str, username: str) -> None:
    page.goto(f"{base_url}/register/")
    # Enabled once the vendored sm-crypto and keyexchange.js have loaded and set up.
    expect(page.locator("#register-submit")).to_be_enabled()
    page.fill("#id_username", username)
    page.fill("#id_password1", TEST_PASSWORD)
    page.fill("#id_password2", TEST_PASSWORD)


def test_registration_works_without_typing_a_key_and_each_gets_its_own(
    live_server, deployed, browser: Browser, tmp_path: Path
):
    base = live_server.url
    page_errors: list[str] = []
    keys = {}
    for name in (f"gen-a-{uuid.uuid4().hex[:6]}", f"gen-b-{uuid.uuid4().hex[:6]}"):
        context = browser.new_context(accept_downloads=True)
        context.on("weberror", lambda error: page_errors.append(str(error.error)))
        page = context.new_page()
        fill_in(page, base, name)
        # A key is there as the page loads, read-only, with the note to save it.
        key_field = page.locator("#id_sm4_key")
        expect(key_field).to_have_value(re.compile(r"^[0-9a-f]{32}$"))
        expect(key_field).to_have_attribute("readonly", "")
        expect(page.locator("#key-generated-note")).to_be_visible()
        key = key_field.input_value()
        with page.expect_download() as download:
            page.click("#download-key")
        saved = tmp_path / download.value.suggested_filename
        download.value.save_as(saved)
        assert download.value.suggested_filename == f"{name}.sm4"
        assert saved.read_text() == key + "\n"

        with page.expect_request(lambda r: r.method == "POST" and "/register/" in r.url) as sent:
            page.click("#register-submit")
        page.wait_for_url("**/register/progress/")
        assert key not in (sent.value.post_data or "").lower()
        expect(page.locator("#registration-progress")).to_have_attribute("data-state", "confirmed")
        owner = owner_by_username(name)
        assert owner_key_bytes(owner_key_current(owner)) == bytes.fromhex(key)
        keys[name] = key
        context.close()
    assert len(set(keys.values())) == 2
    assert not page_errors, page_errors


def test_a_typed_word_is_refused_and_a_generated_key_offered_again(
    live_server, deployed, browser: Browser
):
    base = live_server.url
    context = browser.new_context()
    page = context.new_page()
    name = f"typed-{uuid.uuid4().hex[:6]}"
    fill_in(page, base, name)
    page.click("#type-own-key")
    expect(page.locator("#id_sm4_key")).to_have_value("")
    expect(page.locator("#key-generated-note")).to_be_hidden()
    page.fill("#id_sm4_key", b"mysecretpassword".hex())
    page.click("#register-submit")
    expect(page.locator("#key-server-error")).to_contain_text("let the portal generate your key")
    assert not Owner.objects.filter(user__username=name).exists()
    # The page generated a new key; submitting it (passwords typed again) registers.
    expect(page.locator("#id_sm4_key")).to_have_value(re.compile(r"^[0-9a-f]{32}$"))
    page.fill("#id_password1", TEST_PASSWORD)
    page.fill("#id_password2", TEST_PASSWORD)
    page.click("#register-submit")
    page.wait_for_url("**/register/progress/")
    assert Owner.objects.filter(user__username=name).exists()
    context.close()
