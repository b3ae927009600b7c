"""My data, shared with me, and the record page: the verdict first, content only if verified."""

import html
import json
import re
import uuid
from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.models import Record, Verdict
from sharing.services.anchoring import records_reanchor
from sharing.services.grants import grant_create, grant_revoke
from stack.anvil import free_port
from tests.pages.conftest import image, odometry
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db


@pytest.fixture
def alice(make_robot):
    return make_robot("alice")


@pytest.fixture
def bob(make_owner):
    return make_owner("bob")


@pytest.fixture
def granted(alice, bob, django_capture_on_commit_callbacks):
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)


def _rows(html: str) -> list[str]:
    return re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', html)


# --- lists --------------------------------------------------------------------------------


def test_my_data_lists_filters_and_pages(client, alice, make_robot, upload):
    odom = [upload(alice, seq, plaintext=odometry("alice", seq, 0)) for seq in (1, 2, 3)]
    img = upload(alice, 4, plaintext=image("alice"), topic="/cam", data_type="sensor_msgs/Image")
    pending = upload(alice, 5, anchor=False, topic="/cam", data_type="sensor_msgs/Image")
    other = make_robot("zed")
    foreign = upload(other, 1)
    client.force_login(alice.owner.user)
    url = reverse("records")

    page = client.get(url)
    html = page.content.decode()
    assert page.status_code == 200
    assert set(_rows(html)) == {str(r.id) for r in [*odom, img, pending]}
    assert str(foreign.id) not in html
    assert odom[0].tx_hash in html
    assert f"block {odom[0].block_number}<" in html
    assert "5 of 5 records" in html

    assert set(_rows(client.get(url, {"topic": "/cam"}).content.decode())) == {
        str(img.id),
        str(pending.id),
    }
    by_type = client.get(url, {"data_type": "nav_msgs/Odometry"}).content.decode()
    assert set(_rows(by_type)) == {str(r.id) for r in odom}
    assert _rows(client.get(url, {"status": "pending"}).content.decode()) == [str(pending.id)]
    assert len(_rows(client.get(url, {"status": "anchored"}).content.decode())) == 4

    Record.objects.filter(pk=odom[0].pk).update(captured_at=timezone.now() - timedelta(days=3))
    since = (timezone.now() - timedelta(days=1)).strftime("%Y-%m-%dT%H:%M")
    until = (timezone.now() - timedelta(days=2)).strftime("%Y-%m-%dT%H:%M")
    assert str(odom[0].id) not in _rows(client.get(url, {"since": since}).content.decode())
    assert _rows(client.get(url, {"until": until}).content.decode()) == [str(odom[0].id)]
    bad_range = client.get(url, {"since": since, "until": until}).content.decode()
    assert "after its end" in bad_range

    paged = client.get(url, {"page": 2})
    assert paged.status_code == 200  # past the last page: the last page


def test_my_data_pagination(client, alice, upload, monkeypatch):
    monkeypatch.setattr("sharing.views.records.RECORDS_PER_PAGE", 2)
    for seq in (1, 2, 3):
        upload(alice, seq, anchor=False)
    client.force_login(alice.owner.user)
    first = client.get(reverse("records")).content.decode()
    assert len(_rows(first)) == 2
    assert "Page 1 of 2" in first
    # The next page is the one the link names: the list as it was when opened (its `top`).
    (next_link,) = re.findall(r'href="([^"]*)" rel="next"', first)
    second = client.get(reverse("records") + html.unescape(next_link)).content.decode()
    assert len(_rows(second)) == 1
    assert set(_rows(first)).isdisjoint(_rows(second))


def test_shared_with_me(client, alice, bob, upload, django_capture_on_commit_callbacks):
    record = upload(alice, 1)
    client.force_login(bob.user)
    assert _rows(client.get(reverse("shared")).content.decode()) == []
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    html = client.get(reverse("shared")).content.decode()
    assert _rows(html) == [str(record.id)]
    assert "Owners sharing with you: <strong>alice</strong>" in html
    assert _rows(client.get(reverse("shared"), {"owner": "alice"}).content.decode()) == [
        str(record.id)
    ]
    assert _rows(client.get(reverse("records")).content.decode()) == []
    grant_revoke(owner=alice.owner, grantee=bob)
    assert _rows(client.get(reverse("shared")).content.decode()) == []


# --- the record page ----------------------------------------------------------------------


def test_verified_odometry_record(client, alice, upload):
    earlier = [upload(alice, seq, plaintext=odometry("alice", seq, seq / 2)) for seq in (1, 2)]
    record = upload(alice, 3, plaintext=odometry("alice", 3.0, 1.5, marker="frame-xyz"))
    client.force_login(alice.owner.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    html = page.content.decode()
    assert page.status_code == 200
    assert "no-store" in page["Cache-Control"]
    assert 'data-verdict="verified"' in html
    assert html.index('id="verdict"') < html.index("frame-xyz")  # the verdict comes first
    verdict = Verdict.objects.filter(record=record).latest("created_at")
    assert verdict.outcome == "verified"
    assert verdict.chain_digest == record.digest
    assert record.digest in html
    assert f'data-testid="verified-block">{verdict.block_number}<' in html
    assert "odometry-table" in html
    assert "x 3.0000, y 1.5000, z 0.0000" in html
    assert "45.0°" in html  # yaw of the quaternion
    assert reverse("record-raw", args=[record.id]) in html
    # The trajectory is the series plot of the record's robot and topic, around it.
    assert "data-series-plot" in html
    assert f'data-robot="{record.robot_id}"' in html
    assert 'data-fields="position.x,position.y" data-mode="xy" data-units="m"' in html

    body = client.get(SERIES, _around(record)).json()
    assert (body["source_records"], body["verified"], body["refused"]) == (3, 3, 0)
    assert [point[1:] for point in body["points"]] == [[1.0, 0.5], [2.0, 1.0], [3.0, 1.5]]
    # Each plotted neighbour went through its own integrity check.
    assert all(Verdict.objects.filter(record=r, outcome="verified").exists() for r in earlier)


def test_a_record_anchored_while_its_page_loads_shows_its_block(client, alice, upload, monkeypatch):
    """The page read the row before anchoring wrote its block; the worker's check then found
    the root on chain: the page shows the block anchoring wrote, not the stale row's blank."""
    from sharing.views import record as views

    record = upload(alice, 1)
    assert record.block_number is not None
    opened_once = views.record_open

    def stale_row(**kwargs):
        opened = opened_once(**kwargs)
        opened.record.block_number = None  # as it was read before the anchor landed
        opened.record.tx_hash = ""
        return opened

    monkeypatch.setattr(views, "record_open", stale_row)
    client.force_login(alice.owner.user)
    html = client.get(reverse("record-detail", args=[record.id])).content.decode()
    assert 'data-verdict="verified"' in html
    assert f'data-testid="anchored-block">{record.block_number}<' in html
    assert record.tx_hash in html


def test_trajectory_leaves_out_records_that_fail_their_check(client, alice, upload):
    first = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    record = upload(alice, 2, plaintext=odometry("alice", 1, 1))
    tamper(first)
    client.force_login(alice.owner.user)
    body = client.get(SERIES, _around(record)).json()
    assert [point[1:] for point in body["points"]] == [[1.0, 1.0]]
    assert body["refused"] == 1


SERIES = "/api/v1/records/series/"


def _around(record: Record) -> dict[str, str]:
    return {
        "robot": str(record.robot_id),
        "topic": record.topic,
        "fields": "position.x,position.y",
        "since": (record.captured_at - timedelta(minutes=1)).isoformat(),
        "until": (record.captured_at + timedelta(minutes=1)).isoformat(),
    }


def test_verified_image_record_shows_the_image(client, alice, upload):
    record = upload(alice, 1, plaintext=image("alice"), topic="/cam", data_type="sensor_msgs/Image")
    client.force_login(alice.owner.user)
    html = client.get(reverse("record-detail", args=[record.id])).content.decode()
    assert 'data-verdict="verified"' in html
    assert re.search(r'<img src="data:image/png;base64,iVBORw0KGgo[A-Za-z0-9+/=]+"', html)
    assert 'width="4" height="3"' in html
    assert "base64 characters, above" in html
    assert "data-series-plot" not in html


def test_raw_json_download(client, alice, upload):
    plaintext = odometry("alice", 1, 2)
    record = upload(alice, 1, plaintext=plaintext)
    client.force_login(alice.owner.user)
    page = client.get(reverse("record-raw", args=[record.id]))
    assert page.status_code == 200
    assert page.content == plaintext
    assert page["Content-Type"] == "application/json"
    assert page["Content-Disposition"].startswith('attachment; filename="robot_odom-1-')
    assert Verdict.objects.filter(record=record, outcome="verified").count() == 1


def test_tampered_record_says_so_and_shows_nothing(client, alice, bob, granted, upload):
    record = upload(alice, 1, plaintext=odometry("alice", 7.25, 0, marker="secret-frame"))
    tamper(record)
    for viewer in (alice.owner, bob):
        client.force_login(viewer.user)
        page = client.get(reverse("record-detail", args=[record.id]))
        html = page.content.decode()
        assert page.status_code == 409
        assert 'data-verdict="tampered"' in html
        assert "<h1>TAMPERED</h1>" in html
        assert "secret-frame" not in html
        assert "7.25" not in html
        verdict = Verdict.objects.filter(record=record, access__viewer=viewer).latest("created_at")
        assert verdict.outcome == "tampered"
        assert verdict.computed_digest in html
        assert verdict.chain_digest in html
        assert verdict.computed_digest != verdict.chain_digest
        raw = client.get(reverse("record-raw", args=[record.id]))
        assert raw.status_code == 409
        assert raw.json()["error"] == "tampered"
        assert b"secret-frame" not in raw.content
        body = client.get(SERIES, _around(record)).json()
        assert (body["refused"], body["points"]) == (1, [])
    client.force_login(alice.owner.user)
    assert "TAMPERED" in client.get(reverse("records")).content.decode()
    assert "TAMPERED" in client.get(reverse("records"), {"status": "tampered"}).content.decode()


def test_record_not_anchored_yet(client, alice, upload):
    record = upload(alice, 1, anchor=False, plaintext=odometry("alice", 0, 0, marker="frame-zq9"))
    client.force_login(alice.owner.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    html = page.content.decode()
    assert page.status_code == 409
    assert 'data-verdict="not_anchored_yet"' in html
    assert "Not anchored yet" in html
    assert "frame-zq9" not in html
    assert client.get(reverse("record-raw", args=[record.id])).status_code == 409


def test_record_whose_anchoring_failed_says_so(
    client, alice, bob, granted, upload, settings, django_capture_on_commit_callbacks
):
    settings.ANCHOR_MAX_ATTEMPTS = 0  # the worker gives up on the record at once
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0, marker="frame-fx3"))
    assert record.status == Record.Status.FAILED
    assert record.failure_reason == "not anchored after 0 attempts"
    for viewer in (alice.owner, bob):
        client.force_login(viewer.user)
        page = client.get(reverse("record-detail", args=[record.id]))
        html = page.content.decode()
        assert page.status_code == 409
        assert 'data-verdict="anchoring_failed"' in html
        assert "<title>Anchoring failed" in html
        assert "<h1>Anchoring failed</h1>" in html
        assert "not anchored after 0 attempts" in html
        assert "operator of the portal can re-anchor it" in html
        assert "Not anchored yet" not in html
        assert "try again shortly" not in html
        assert "frame-fx3" not in html
        raw = client.get(reverse("record-raw", args=[record.id]))
        assert raw.status_code == 409
        assert raw.json()["error"] == "anchoring_failed"

    # Once an operator re-anchors it, it is checked and shown like any other record.
    settings.ANCHOR_MAX_ATTEMPTS = 20
    with django_capture_on_commit_callbacks(execute=True):
        assert records_reanchor(record_ids=[record.pk]) == 1
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 200
    assert "frame-fx3" in page.content.decode()


def _refusal(page) -> str:
    """What a refused page says: its verdict section, or the whole body of a JSON answer."""
    text = page.content.decode()
    found = re.search(r'<section class="verdict.*?</section>', text, re.S)
    return found.group(0) if found else text


def test_records_of_others_are_out_of_reach(client, alice, bob, upload):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0, marker="private-frame"))
    client.force_login(bob.user)
    missing_id = uuid.uuid4()
    for name in ("record-detail", "record-raw"):
        page = client.get(reverse(name, args=[record.id]))
        assert page.status_code == 404, name
        assert b"private-frame" not in page.content
        # One answer whether the record exists or not (issue 37): the same status and body.
        missing = client.get(reverse(name, args=[missing_id]))
        assert missing.status_code == 404, name
        assert _refusal(missing) == _refusal(page), name
    html = client.get(reverse("record-detail", args=[record.id])).content.decode()
    assert 'data-verdict="not_found"' in html
    assert str(record.digest) not in html
    assert Verdict.objects.filter(record=record, access__viewer=bob, outcome="no_access").exists()
    assert client.get("/records/not-a-uuid/").status_code == 404


def test_grantee_sees_until_revoked(client, alice, bob, granted, upload):
    record = upload(alice, 1, plaintext=image("alice"), topic="/cam", data_type="sensor_msgs/Image")
    client.force_login(bob.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 200
    assert "data:image/png;base64," in page.content.decode()
    grant_revoke(owner=alice.owner, grantee=bob)  # its chain call is still pending
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 403  # told why, as the grantee the record was shared with
    assert "access revoked by owner" in html.unescape(page.content.decode()).lower()
    assert "data:image/png" not in page.content.decode()


def test_verification_unavailable(client, alice, upload, settings):
    record = upload(alice, 1)
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    settings.VERIFY_TIMEOUT = 5
    client.force_login(alice.owner.user)
    page = client.get(reverse("record-detail", args=[record.id]))
    assert page.status_code == 503
    assert 'data-verdict="unavailable"' in page.content.decode()
    raw = client.get(reverse("record-raw", args=[record.id]))
    assert raw.status_code == 503
    assert json.loads(raw.content)["error"] == "unavailable"
