"""One record filter: the record pages and the API list the same records for the same filters.

Capture times are half-open on both, [since, until): a record captured exactly at `until`
is left out, one captured exactly at `since` is in.
"""

import re
from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.models import Record
from sharing.selectors.records import record_list_filtered, record_list_owned
from tests.api.conftest import RECORDS, session_client

pytestmark = pytest.mark.django_db

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _at(minutes: int) -> datetime:
    return NOON + timedelta(minutes=minutes)


def _page_time(minutes: int) -> str:
    return _at(minutes).strftime("%Y-%m-%dT%H:%M")


def _api_time(minutes: int) -> str:
    return _at(minutes).isoformat().replace("+00:00", "Z")


@pytest.fixture
def records(make_robot, upload) -> dict[str, Record]:
    """Five records of alice a minute apart: anchored, pending, tampered and failed ones."""
    alice = make_robot("alice")

    def send(seq: int, minutes: int, *, topic: str, data_type: str, anchor: bool = True) -> Record:
        time = _api_time(minutes)
        return upload(alice, seq, anchor=anchor, time=time, topic=topic, data_type=data_type)

    made = {
        "odom0": send(1, 0, topic="/odom", data_type="nav_msgs/Odometry"),
        "chat1": send(2, 1, topic="/chatter", data_type="std_msgs/String"),
        "odom2": send(3, 2, topic="/odom", data_type="nav_msgs/Odometry"),
        "chat3": send(4, 3, topic="/chatter", data_type="std_msgs/String"),
        "odom4": send(5, 4, topic="/odom", data_type="nav_msgs/Odometry", anchor=False),
    }
    Record.objects.filter(pk=made["chat1"].pk).update(tampered_at=timezone.now())
    Record.objects.filter(pk=made["odom2"].pk).update(status=Record.Status.FAILED)
    return made


def _page_ids(client, params: dict[str, str]) -> list[str]:
    page = client.get(reverse("records"), params)
    assert page.status_code == 200
    return re.findall(
        r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', page.content.decode()
    )


def _api_ids(api, params: dict[str, str]) -> list[str]:
    answer = api.get(RECORDS, params)
    assert answer.status_code == 200, answer.content
    return [record["id"] for record in answer.json()["results"]]


# (page parameters, API parameters, the records both list, newest first)
CASES = [
    ({}, {}, ["odom4", "chat3", "odom2", "chat1", "odom0"]),
    ({"topic": "/odom"}, {"topic": "/odom"}, ["odom4", "odom2", "odom0"]),
    ({"data_type": "std_msgs/String"}, {"type": "std_msgs/String"}, ["chat3", "chat1"]),
    ({"status": "pending"}, {"status": "pending"}, ["odom4"]),
    ({"status": "failed"}, {"status": "failed"}, ["odom2"]),
    ({"status": "anchored"}, {"status": "anchored"}, ["chat3", "chat1", "odom0"]),
    ({"status": "tampered"}, {"status": "tampered"}, ["chat1"]),
    # The boundaries: `since` is in, `until` is out.
    ({"since": _page_time(1)}, {"since": _api_time(1)}, ["odom4", "chat3", "odom2", "chat1"]),
    ({"until": _page_time(1)}, {"until": _api_time(1)}, ["odom0"]),
    (
        {"since": _page_time(1), "until": _page_time(3)},
        {"since": _api_time(1), "until": _api_time(3)},
        ["odom2", "chat1"],
    ),
    (
        {"since": _page_time(2), "until": _page_time(2)},
        {"since": _api_time(2), "until": _api_time(2)},
        [],
    ),
    (
        {"topic": "/odom", "status": "anchored", "until": _page_time(4)},
        {"topic": "/odom", "status": "anchored", "until": _api_time(4)},
        ["odom0"],
    ),
]


def test_pages_and_api_list_the_same_records(client, records):
    owner = records["odom0"].owner
    client.force_login(owner.user)
    api = session_client(owner)
    for page_params, api_params, expected in CASES:
        wanted = [str(records[name].pk) for name in expected]
        assert _page_ids(client, page_params) == wanted, page_params
        assert _api_ids(api, api_params) == wanted, api_params
        # And the selector both call, given the same values.
        selector_params = {
            "data_type" if name == "type" else name: _at_or_text(value)
            for name, value in api_params.items()
        }
        listed = record_list_filtered(record_list_owned(owner), **selector_params)
        assert [str(record.pk) for record in listed] == wanted, selector_params


def _at_or_text(value: str) -> datetime | str:
    try:
        return datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        return value


def test_the_page_says_the_end_of_the_range_is_left_out(client, records):
    client.force_login(records["odom0"].owner.user)
    html = client.get(reverse("records")).content.decode()
    assert "Before (UTC)" in html
    assert "Until (UTC)" not in html


def test_the_api_refuses_an_unknown_status(client, records):
    answer = session_client(records["odom0"].owner).get(RECORDS, {"status": "lost"})
    assert answer.status_code == 400
    assert answer.json()["error"] == "invalid_request"


@pytest.mark.parametrize(
    "moment",
    ["0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59-14:00"],
    ids=["year-1-east", "year-9999-west"],
)
def test_a_time_outside_the_years_utc_can_hold_is_a_form_error_on_every_page(
    client, records, moment
):
    """A time whose UTC falls before year 1 or after 9999 overflowed in the query (500) on
    every page with a period filter; it is the form's error, as the API's 400."""
    record = next(iter(records.values()))
    client.force_login(record.owner.user)
    pages = [
        reverse("records"),
        reverse("shared"),
        reverse("audit"),
        reverse("access-log"),
        reverse("access-log-csv"),
        reverse("records-delete"),
        reverse("record-gallery", args=[record.id]),
    ]
    for page in pages:
        for name in ("since", "until"):
            answer = client.get(page, {name: moment})
            assert answer.status_code in (200, 400, 404), (page, name, answer.status_code)
            if answer.streaming:  # the CSV streams: read it to its end
                b"".join(answer.streaming_content)
