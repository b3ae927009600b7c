"""The record lists page by capture time (issue 48): a page stays what it was while robots
upload, a banner counts the records captured since the list was opened and links to the
newest, and a cursor that is no cursor gives the first page, never a 500."""

import re
from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse

from sharing.services.grants import grant_create

pytestmark = pytest.mark.django_db

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _at(seconds: float) -> str:
    return (NOON + timedelta(seconds=seconds)).isoformat().replace("+00:00", "Z")


def _rows(html: str) -> list[str]:
    return re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', html)


def _link(html: str, testid: str) -> str:
    href = re.search(rf'href="([^"]+)"[^>]*data-testid="{testid}"', html)
    assert href, testid
    return href.group(1).replace("&amp;", "&")


@pytest.fixture
def small_pages(monkeypatch):
    monkeypatch.setattr("sharing.views.records.RECORDS_PER_PAGE", 2)


@pytest.mark.parametrize("shared", [False, True], ids=["my-data", "shared-with-me"])
def test_pages_stay_while_the_robot_uploads(
    client, make_robot, upload, small_pages, shared, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    made = [upload(alice, n, anchor=False, time=_at(60 * n)) for n in range(1, 6)]
    newest_first = [str(record.pk) for record in reversed(made)]
    if shared:
        bob = make_robot("bob")
        with django_capture_on_commit_callbacks(execute=True):
            grant_create(owner=alice.owner, grantee=bob.owner)
        client.force_login(bob.owner.user)
        url = reverse("shared")
    else:
        client.force_login(alice.owner.user)
        url = reverse("records")

    first = client.get(url).content.decode()
    assert _rows(first) == newest_first[:2]
    assert "5 of 5 records" in first
    assert 'data-testid="newer-records"' not in first
    second_url = _link(first, "page-next")
    second = client.get(url + second_url).content.decode()
    assert _rows(second) == newest_first[2:4]
    assert re.search(r'data-testid="page-current">2<', second)

    # The robot uploads three more, newer, while the owner is on page 2.
    for n in range(6, 9):
        upload(alice, n, anchor=False, time=_at(60 * n))
    again = client.get(url + second_url).content.decode()
    assert _rows(again) == newest_first[2:4]
    assert "5 of 5 records" in again
    banner = re.search(r'data-testid="newer-records">([^<]*)<', again)
    assert banner is not None
    assert banner.group(1).startswith("3 newer records")
    # Next and Last go on in the same list; Previous and First come back to the same first page.
    third = client.get(url + _link(again, "page-next")).content.decode()
    assert _rows(third) == newest_first[4:]
    assert 'data-testid="page-next"' not in third
    assert _rows(client.get(url + _link(again, "page-last")).content.decode()) == newest_first[4:]
    back = client.get(url + _link(third, "page-previous")).content.decode()
    assert _rows(back) == newest_first[2:4]
    assert _rows(client.get(url + _link(back, "page-first")).content.decode()) == newest_first[:2]
    # The banner's link is the list as it is now, newest first.
    now = client.get(url + _link(again, "show-newest")).content.decode()
    assert len(_rows(now)) == 2
    assert _rows(now)[1] not in newest_first
    assert "8 of 8 records" in now


def test_oldest_first_pages_by_capture_too(client, make_robot, upload, small_pages):
    alice = make_robot("alice")
    made = [str(upload(alice, n, anchor=False, time=_at(60 * n)).pk) for n in range(1, 5)]
    client.force_login(alice.owner.user)
    url = reverse("records")
    first = client.get(url, {"sort": "captured"}).content.decode()
    assert _rows(first) == made[:2]
    upload(alice, 5, anchor=False, time=_at(0))  # an older capture, from a robot's spool
    second = client.get(url + _link(first, "page-next")).content.decode()
    assert _rows(second) == made[2:]


@pytest.mark.parametrize(
    "params",
    [
        {"after": "yesterday"},
        {"after": "2026-03-01T12:00:00.000000Z_nothex"},
        {"before": "2026-13-01T12:00:00.000000Z_" + "0" * 32},
        {"top": "x" * 5000},
        {"top": "_"},
        {"after": "2026-03-01T12:00:00.000000Z_" + "0" * 32 + "_1"},
        {"page": "last", "sort": "captured", "top": "\x00"},
    ],
)
def test_a_bad_cursor_gives_the_first_page(client, make_robot, upload, small_pages, params):
    alice = make_robot("alice")
    made = [upload(alice, n, anchor=False, time=_at(60 * n)) for n in range(1, 4)]
    client.force_login(alice.owner.user)
    page = client.get(reverse("records"), params)
    assert page.status_code == 200
    html = page.content.decode()
    assert "That page link is not valid: showing the newest records." in html
    expected = [str(r.pk) for r in (reversed(made) if "sort" not in params else made)]
    assert _rows(html) == expected[:2]


def test_a_cursor_past_the_end_is_an_empty_page(client, make_robot, upload, small_pages):
    alice = make_robot("alice")
    upload(alice, 1, anchor=False, time=_at(60))
    client.force_login(alice.owner.user)
    page = client.get(reverse("records"), {"after": "946684800000000_" + "0" * 32})  # 2000-01-01
    assert page.status_code == 200
    assert _rows(page.content.decode()) == []
