"""The export pages in Chromium, at 1280x900 and on a 390x844 phone: an owner exports a
selection, follows its progress (the bar moves while the worker checks records) and downloads
the MCAP file and the proof bundle, which the standalone verifier accepts.

No Celery worker: the form's export runs inline (eager), and the progress part plays the
worker itself, moving a running export's count and then running it (sharing.exports).
"""

import json
from datetime import timedelta
from pathlib import Path

import pytest
from django.utils import timezone
from playwright.sync_api import Browser, Page, expect

from authros_verify import ChainReader, verify
from sharing.exports.run import export_run
from sharing.models import Export
from sharing.selection import RecordSelection
from sharing.services.uploads import record_create_batch
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = [pytest.mark.browser, pytest.mark.django_db(transaction=True)]

DESKTOP = {"width": 1280, "height": 900}
PHONE = {"width": 390, "height": 844}


def _no_horizontal_scroll(page: Page) -> None:
    width = page.evaluate("document.documentElement.scrollWidth")
    assert width <= page.viewport_size["width"], width


def test_export_page_with_progress_on_desktop_and_phone(
    live_server, deployed, make_robot, browser: Browser, artifacts: Path
):
    alice = make_robot("alice")
    envelopes = [
        alice.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            plaintext=json.dumps({"K": {"data": f"hello {seq}"}}).encode(),
        )
        for seq in (1, 2)
    ]
    record_create_batch(robot=alice.robot, envelopes=envelopes)  # anchored on commit, inline

    context = browser.new_context(viewport=DESKTOP, accept_downloads=True)
    page = context.new_page()
    base = live_server.url
    page.goto(f"{base}/login/")
    page.fill("#id_username", "alice")
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")

    # --- desktop: the form, an export, its files ---------------------------------------------
    page.click('[data-testid="nav-exports"]')
    page.wait_for_url("**/exports/")
    expect(page.get_by_label("/chatter")).to_be_visible()
    _no_horizontal_scroll(page)
    page.screenshot(path=artifacts / "export-form-desktop.png", full_page=True)
    # The count before submitting (static/portal/export_count.js on the count API).
    expect(page.get_by_test_id("export-count")).to_contain_text("holds 2 records")
    page.get_by_label("/chatter").check()
    expect(page.get_by_test_id("export-count")).to_have_attribute("data-count", "2")
    page.fill("#id_since", "2030-01-01T00:00")
    page.locator("#id_since").dispatch_event("change")
    expect(page.get_by_test_id("export-count")).to_contain_text("No record you may view")
    page.fill("#id_since", "")
    page.locator("#id_since").dispatch_event("change")
    expect(page.get_by_test_id("export-count")).to_contain_text("holds 2 records")
    page.click("#export-submit")
    page.wait_for_url("**/exports/*/")
    expect(page.get_by_test_id("export-status")).to_have_text("ready")
    expect(page.get_by_test_id("export-summary")).to_contain_text("2 of 2 records checked")
    with page.expect_download() as mcap_download:
        page.get_by_test_id("download-mcap").click()
    with page.expect_download() as bundle_download:
        page.get_by_test_id("download-bundle").click()
    mcap = Path(mcap_download.value.path()).read_bytes()
    bundle = Path(bundle_download.value.path()).read_bytes()
    assert mcap_download.value.suggested_filename.endswith(".mcap")
    report = verify(bundle, chain=ChainReader(deployed.w3), mcap=mcap, contract=deployed.address)
    assert report.ok, report.problems
    # The selection and the command that checks the files against this chain.
    expect(page.get_by_test_id("export-selection")).to_contain_text("/chatter")
    command = page.get_by_test_id("verify-command")
    expect(command).to_contain_text(f"--contract {deployed.address}")
    expect(command).to_contain_text(f"--chain-id {deployed.w3.eth.chain_id}")
    expect(command).to_contain_text(mcap_download.value.suggested_filename)
    _no_horizontal_scroll(page)
    page.screenshot(path=artifacts / "export-ready-desktop.png", full_page=True)

    # --- phone: an export in progress, its bar moving, then ready ----------------------------
    running = Export.objects.create(
        requester=alice.owner,
        selection=RecordSelection().as_json(),
        status=Export.Status.RUNNING,
        total=4,
        processed=1,
        expires_at=timezone.now() + timedelta(hours=1),
    )
    phone = context.new_page()
    phone.set_viewport_size(PHONE)
    phone.goto(f"{base}/exports/{running.pk}/")
    progress = phone.get_by_test_id("export-progress")
    expect(phone.locator("#export-bar")).to_have_attribute("value", "25")
    _no_horizontal_scroll(phone)
    phone.screenshot(path=artifacts / "export-running-phone.png", full_page=True)
    Export.objects.filter(pk=running.pk).update(processed=3)  # the worker moves on
    expect(progress).to_have_attribute("data-percent", "75")
    expect(phone.get_by_test_id("export-summary")).to_contain_text("3 of 4 records checked")
    export_run(export_id=running.pk)  # ... and finishes: the page reloads with the files
    expect(phone.get_by_test_id("download-mcap")).to_be_visible()
    expect(phone.get_by_test_id("export-status")).to_have_text("ready")
    expect(phone.get_by_test_id("verify-command")).to_be_visible()
    _no_horizontal_scroll(phone)
    phone.screenshot(path=artifacts / "export-ready-phone.png", full_page=True)
    phone.goto(f"{base}/exports/")
    expect(phone.get_by_test_id("export-row")).to_have_count(2)
    _no_horizontal_scroll(phone)
    phone.screenshot(path=artifacts / "exports-phone.png", full_page=True)
    context.close()
