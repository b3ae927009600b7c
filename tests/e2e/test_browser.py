"""Issue 4 end to end in Chromium: two owners register, A's robot uploads an image, A grants
B, B sees the verified image, A revokes, B is refused; a tampered record shows TAMPERED.

Everything an owner does goes through the pages; only the robot's upload is an HTTP call
(`POST /api/v1/records/`, as the ROS agent sends it) and the tampering is done on disk.
A screenshot of every step is kept in test-artifacts/e2e/.
"""

import base64
import re
import time
import uuid
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import genpy
import numpy as np
import pytest
import requests
from playwright.sync_api import Browser, Page, Response, expect
from sensor_msgs.msg import Image

from accounts.selectors import owner_by_username, owner_key_bytes, owner_key_current
from core.redis_client import get_redis
from ros_agent.extractors import extract
from ros_agent.wrapping import capture_time, envelope_header, record_json
from sharing.cache import _key as cache_key
from sharing.models import Record
from sharing.storage import envelope_storage
from smcrypto import envelope
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.screenshots import Screenshots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]

# A's key, typed into the register page, so that the test can seal for A's robot (it must
# look random: the portal refuses sequences such as 00112233...).
KEY_A = "c4e1a97d0b5f2368e9d7b41a6f0c38e2"
IMAGE_TOPIC = "/robot/complicatedImage"
IMAGE_TYPE = "sensor_msgs/Image"
IMAGE_WIDTH, IMAGE_HEIGHT = 64, 48
CHAIN_TIMEOUT_MS = 90_000


def reload_until(page: Page, ready: Callable[[], bool], *, what: str, timeout: float = 90) -> None:
    """Reload a server-rendered page until `ready()` holds on it."""
    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:.0f}s waiting for {what}")
        time.sleep(0.5)
        page.reload()


def register(page: Page, base_url: str, username: str, *, key: str | None) -> str:
    """Fill in the register page and submit it; return the key (typed, or generated)."""
    page.goto(f"{base_url}/register/")
    # Enabled only once the vendored sm-crypto and keyexchange.js have loaded and set up.
    expect(page.locator("#register-submit")).to_be_enabled()
    page.fill("#id_username", username)
    page.fill("#id_password1", TEST_PASSWORD)
    page.fill("#id_password2", TEST_PASSWORD)
    if key is None:
        page.click("#generate-key")
        key = page.input_value("#id_sm4_key")
    else:
        page.click("#type-own-key")
        page.fill("#id_sm4_key", key)
    assert re.fullmatch(r"[0-9a-f]{32}", key)
    return key


def submit_registration(page: Page) -> str:
    """Submit the register form; return the body that crossed the network."""
    with page.expect_request(lambda r: r.method == "POST" and "/register/" in r.url) as sent:
        page.click("#register-submit")
    page.wait_for_url("**/register/progress/")
    return sent.value.post_data or ""


def wait_registered(page: Page) -> None:
    expect(page.locator("#registration-progress")).to_have_attribute(
        "data-state", "confirmed", timeout=CHAIN_TIMEOUT_MS
    )
    expect(page.locator("#progress-summary")).to_contain_text("registered on chain")


def camera_image(seq: int) -> Image:
    """A sensor_msgs/Image as a camera driver publishes it: a colour gradient, rgb8."""
    x = np.linspace(0, 255, IMAGE_WIDTH, dtype=np.uint8)
    y = np.linspace(0, 255, IMAGE_HEIGHT, dtype=np.uint8)
    pixels = np.zeros((IMAGE_HEIGHT, IMAGE_WIDTH, 3), np.uint8)
    pixels[..., 0] = x[np.newaxis, :]
    pixels[..., 1] = y[:, np.newaxis]
    pixels[..., 2] = (seq * 97) % 256
    msg = Image(height=IMAGE_HEIGHT, width=IMAGE_WIDTH, encoding="rgb8", is_bigendian=0)
    msg.header.seq = seq
    msg.header.stamp = genpy.Time.from_sec(time.time())
    msg.header.frame_id = "camera"
    msg.step = IMAGE_WIDTH * 3
    msg.data = pixels.tobytes()
    return msg


def sealed_image(*, key: bytes, owner: str, robot: str, seq: int) -> bytes:
    """What ros_agent.wrapping.Recorder spools for an image: Fig. 4 JSON, sealed."""
    msg = camera_image(seq)
    captured_at = capture_time(msg, datetime.now(UTC))
    plaintext = record_json(
        data=extract(msg, IMAGE_TYPE),
        owner=owner,
        topic=IMAGE_TOPIC,
        ros_type=IMAGE_TYPE,
        captured_at=captured_at,
    )
    header = envelope_header(
        owner=owner,
        robot=robot,
        topic=IMAGE_TOPIC,
        ros_type=IMAGE_TYPE,
        seq=seq,
        captured_at=captured_at,
    )
    return envelope.seal(key, header, plaintext)


def upload(base_url: str, token: str, data: bytes) -> str:
    """POST one envelope as the agent's uploader does; return the record id."""
    answer = requests.post(
        f"{base_url}/api/v1/records/",
        json={"envelope": base64.b64encode(data).decode("ascii")},
        headers={"Authorization": f"Token {token}"},
        timeout=30,
    )
    assert answer.status_code == 201, answer.text
    return answer.json()["id"]


def tamper_stored_envelope(record_id: str) -> None:
    """Flip one ciphertext byte of the durable copy, and drop the cached copy."""
    record = Record.objects.get(pk=record_id)
    path = envelope_storage().path(record.storage_name)
    with open(path, "r+b") as handle:
        handle.seek(-1, 2)
        last = handle.read(1)
        handle.seek(-1, 2)
        handle.write(bytes([last[0] ^ 0x01]))
    get_redis().delete(cache_key(record.pk))


def open_record(page: Page, base_url: str, record_id: str) -> Response:
    response = page.goto(f"{base_url}/records/{record_id}/")
    assert response is not None
    return response


def expect_no_content(page: Page) -> None:
    """A refused record page shows the verdict and nothing of the record's data."""
    expect(page.locator("#record-image")).to_have_count(0)
    expect(page.locator("#record-json")).to_have_count(0)
    expect(page.locator("#download-raw")).to_have_count(0)


def test_two_owners_share_revoke_and_see_tampering(
    live_server, stack, browser: Browser, artifacts: Path
):
    base = live_server.url
    shot = Screenshots(artifacts)
    suffix = uuid.uuid4().hex[:6]
    alice_name, bob_name = f"alice-{suffix}", f"bob-{suffix}"
    alice = browser.new_context(viewport={"width": 1280, "height": 900})
    bob = browser.new_context(viewport={"width": 1280, "height": 900})
    page_errors: list[str] = []
    failed_assets: list[str] = []
    for context in (alice, bob):
        context.on("weberror", lambda error: page_errors.append(str(error.error)))
        context.on(
            "response",
            lambda r: (
                failed_assets.append(f"{r.status} {r.url}")
                # 304: the browser revalidated a copy it has, which is just as good.
                if "/static/" in r.url and r.status not in (200, 304)
                else None
            ),
        )
    a, b = alice.new_page(), bob.new_page()

    # --- 1. both owners register; A types a key, B generates one in the browser -------------
    typed = register(a, base, alice_name, key=KEY_A)
    shot(a, "a-register-form")
    generated = register(b, base, bob_name, key=None)
    expect(b.locator("#key-generated-note")).to_be_visible()
    shot(b, "b-register-generated-key")
    for page, key in ((a, typed), (b, generated)):
        body = submit_registration(page)
        # The key never crosses the network in plaintext, only its SM2 ciphertext.
        assert key not in body.lower()
        assert re.search(r"key_ciphertext=[0-9a-fA-F]{100,}", body)
    shot(a, "a-registration-progress")
    for page in (a, b):
        wait_registered(page)
    shot(a, "a-registration-confirmed")
    shot(b, "b-registration-confirmed")
    for username, key in ((alice_name, typed), (bob_name, generated)):
        owner = owner_by_username(username)
        assert owner_key_bytes(owner_key_current(owner)) == bytes.fromhex(key)

    a.click("#continue-link")
    expect(a.locator("[data-testid=signed-in-user]")).to_have_text(alice_name)
    shot(a, "a-dashboard")
    # B signs out now and in again later, through the login page.
    b.click("#logout-button")
    b.wait_for_url("**/login/")

    # --- 2. A adds a robot and reads its token once ------------------------------------------
    a.goto(f"{base}/robots/")
    a.fill("#id_name", "turtlebot-e2e")
    a.click("#robot-create-submit")
    token = a.inner_text("#robot-token").strip()
    robot_id = a.inner_text("#robot-id").strip()
    expect(a.locator("#download-config")).to_have_attribute("href", re.compile(re.escape(token)))
    shot(a, "a-robot-added")
    assert token
    assert str(uuid.UUID(robot_id)) == robot_id

    # --- 3. A's robot uploads two camera images; both are anchored ----------------------------
    seal = {"key": bytes.fromhex(KEY_A), "owner": alice_name, "robot": robot_id}
    shared_id = upload(base, token, sealed_image(seq=1, **seal))
    tampered_id = upload(base, token, sealed_image(seq=2, **seal))
    a.goto(f"{base}/records/")
    rows = {
        record_id: a.locator(f"[data-testid=record-row][data-record-id='{record_id}']")
        for record_id in (shared_id, tampered_id)
    }
    reload_until(
        a,
        lambda: all(row.locator(".badge.anchored").count() == 1 for row in rows.values()),
        what="both records anchored on A's My data page",
    )
    expect(rows[shared_id]).to_contain_text(IMAGE_TYPE)
    shot(a, "a-my-data-anchored")

    # --- 4. A grants B by username ----------------------------------------------------------
    a.goto(f"{base}/grants/")
    a.fill("#id_grantee", bob_name)
    a.click("#grant-submit")
    a.click("#grant-confirm-all")  # nothing ticked: all records, no expiry, confirmed
    grant_row = a.locator(f"[data-testid=grant-given-row][data-grantee='{bob_name}']")
    expect(grant_row).to_have_count(1)
    expect(grant_row.get_by_test_id("grant-made-with")).to_have_text("in the portal")
    shot(a, "a-grant-pending")
    reload_until(
        a, lambda: grant_row.get_attribute("data-status") == "active", what="the grant on chain"
    )
    shot(a, "a-grant-active")

    # --- 5. B signs in, finds the record under Shared with me, sees it verified -------------
    b.goto(f"{base}/login/")
    b.fill("#id_username", bob_name)
    b.fill("#id_password", TEST_PASSWORD)
    b.click("#login-submit")
    b.wait_for_url("**/dashboard/")
    b.click("[data-testid=nav-shared]")
    shared_row = b.locator(f"[data-testid=record-row][data-record-id='{shared_id}']")
    expect(shared_row).to_contain_text(alice_name)
    shot(b, "b-shared-with-me")
    with b.expect_navigation() as navigation:
        shared_row.locator("[data-testid=open-record]").click()
    assert navigation.value.status == 200
    expect(b.locator("#verdict")).to_have_attribute("data-verdict", "verified")
    b.wait_for_function(
        "() => { const i = document.getElementById('record-image');"
        " return i && i.complete && i.naturalWidth > 0; }"
    )
    natural = b.locator("#record-image").evaluate("i => [i.naturalWidth, i.naturalHeight]")
    assert natural == [IMAGE_WIDTH, IMAGE_HEIGHT]
    expect(b.locator("#record-json")).to_contain_text(IMAGE_TOPIC)
    shot(b, "b-record-verified")

    # --- 6. A revokes B; B's next view is refused ----------------------------------------------
    a.goto(f"{base}/grants/")
    grant_row.locator("[data-testid=revoke-grant]").click()
    # The portal asks first (tests/e2e/test_grants_page.py has the cancel).
    a.get_by_test_id("revoke-confirm-button").click()
    expect(grant_row).to_have_attribute("data-status", re.compile("revoking|revoked"))
    shot(a, "a-grant-revoked")
    refused = b.reload()
    assert refused is not None
    # B read it before: B is told the owner revoked the access (issue 48), and nothing more.
    assert refused.status == 403
    expect(b.locator("#verdict")).to_have_attribute("data-verdict", "access_ended")
    expect(b.get_by_test_id("refusal-detail")).to_contain_text("Access revoked by owner")
    expect(b.get_by_test_id("to-shared")).to_have_attribute("href", "/shared/")
    expect_no_content(b)
    shot(b, "b-record-refused-after-revocation")
    raw = bob.request.get(f"{base}/records/{shared_id}/raw.json")
    assert raw.status == 403
    assert raw.json()["error"] == "access_ended"

    # B types the URL of another record of A, covered by the grant that ended: told so too
    # (tests/pages/test_access_ended.py: an owner never granted gets the one 404).
    direct = open_record(b, base, tampered_id)
    assert direct.status == 403
    expect(b.locator("#verdict")).to_have_attribute("data-verdict", "access_ended")
    expect_no_content(b)
    expect(b.locator("main")).not_to_contain_text(IMAGE_TOPIC)
    shot(b, "b-other-record-by-url-refused")
    b.goto(f"{base}/shared/")
    expect(b.locator("[data-testid=record-row]")).to_have_count(0)
    shot(b, "b-shared-with-me-empty")

    # --- 7. a tampered record is shown as TAMPERED to its own owner ---------------------------
    tamper_stored_envelope(tampered_id)
    tampered = open_record(a, base, tampered_id)
    assert tampered.status == 409
    expect(a.locator("#verdict")).to_have_attribute("data-verdict", "tampered")
    expect(a.locator("#verdict h1")).to_have_text("TAMPERED")
    expect_no_content(a)
    shot(a, "a-record-tampered")
    # The untouched record still verifies for its owner.
    assert open_record(a, base, shared_id).status == 200
    expect(a.locator("#verdict")).to_have_attribute("data-verdict", "verified")
    expect(a.locator("#record-image")).to_be_visible()
    a.goto(f"{base}/records/")
    expect(rows[tampered_id].locator(".badge.tampered")).to_have_count(1)
    expect(rows[shared_id].locator(".badge.tampered")).to_have_count(0)
    shot(a, "a-my-data-with-tampered")

    # --- 8. the chain's own history of A: grant, revocation, uploads --------------------------
    a.goto(f"{base}/grants/")
    reload_until(
        a, lambda: grant_row.get_attribute("data-status") == "revoked", what="the revocation"
    )
    a.goto(f"{base}/audit/")
    entries = a.locator("[data-testid=audit-entry]")
    expect(entries.and_(a.locator("[data-kind=grant-given]"))).to_contain_text(bob_name)
    expect(entries.and_(a.locator("[data-kind=revoke-given]"))).to_contain_text(bob_name)
    expect(entries.and_(a.locator("[data-kind=upload]")).first).to_be_visible()
    shot(a, "a-audit")

    assert not page_errors, page_errors
    assert not failed_assets, failed_assets
    alice.close()
    bob.close()
