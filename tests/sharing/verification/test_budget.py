"""The budget of integrity checks (sharing/verification/budget.py, CHECK_BUDGET): one budget of
records checked per caller, pages and API alike, in Redis; a read over what is left is refused
whole with 429 and Retry-After and charges nothing; an owner API token spends its owner's; a
batch whose read stopped waiting is not checked and gives its records back."""

from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse

from sharing import tasks
from sharing.models import Access, Record, Verdict
from sharing.verification.budget import check_run
from tests.api.conftest import session_client, token_client
from tests.pages.conftest import odometry
from tests.support.redis_down import redis_nobody_answers

pytestmark = pytest.mark.django_db

SERIES = "/api/v1/records/series/"
T0 = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(minutes=30)


def _iso(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


def _records(upload, setup, count: int, *, first_seq: int = 1) -> list[Record]:
    """`count` odometry records of the robot's /robot/odom, a second apart from T0."""
    return [
        upload(
            setup,
            first_seq + i,
            plaintext=odometry(setup.owner.username, float(i), 0.0),
            time=_iso(T0 + timedelta(seconds=first_seq + i)),
        )
        for i in range(count)
    ]


def _series(setup) -> dict[str, str]:
    return {
        "robot": str(setup.robot.pk),
        "topic": "/robot/odom",
        "fields": "position.x",
        "since": _iso(T0),
        "until": _iso(T0 + timedelta(minutes=5)),
    }


def _content(client, record: Record) -> int:
    return client.get(f"/api/v1/records/{record.pk}/content/").status_code


def test_a_series_over_the_budget_is_refused_whole_and_charges_nothing(alice, upload, settings):
    records = _records(upload, alice, 4)
    settings.CHECK_BUDGET = "4/minute"
    owner = session_client(alice.owner)
    assert _content(owner, records[0]) == 200  # 3 left
    refused = owner.get(SERIES, _series(alice))
    assert refused.status_code == 429, refused.content
    assert refused.json()["error"] == "check_budget_exceeded"
    assert "checks 4 records and 3 of your budget of 4" in refused.json()["detail"]
    # 4 asked, 3 left: the fourth is back within 15 s (4 a minute).
    assert 1 <= int(refused["Retry-After"]) <= 15
    # Nothing was checked, nothing logged but the first record's view.
    assert Verdict.objects.count() == 1
    assert Access.objects.count() == 1
    # Nothing was charged: 3 records are left, and not one more (a day's budget from now on,
    # so that none comes back while the test runs).
    settings.CHECK_BUDGET = "4/day"
    assert [_content(owner, record) for record in records] == [200, 200, 200, 429]
    assert Verdict.objects.count() == 4


def test_a_read_larger_than_the_whole_budget_says_so(alice, upload, settings):
    _records(upload, alice, 3)
    settings.CHECK_BUDGET = "2/hour"
    refused = session_client(alice.owner).get(SERIES, _series(alice))
    assert refused.status_code == 429
    assert "more than the whole budget of 2" in refused.json()["detail"]
    assert refused["Retry-After"] == "3600"


def test_a_read_under_the_budget_charges_the_records_it_checked(alice, upload, settings):
    records = _records(upload, alice, 3)
    settings.CHECK_BUDGET = "5/day"
    owner = session_client(alice.owner)
    answer = owner.get(SERIES, _series(alice))
    assert (answer.status_code, answer.json()["verified"]) == (200, 3)
    assert owner.get(SERIES, _series(alice)).status_code == 429  # 3 asked, 2 left
    assert [_content(owner, record) for record in records] == [200, 200, 429]


def test_pages_and_the_api_draw_on_one_budget(client, alice, upload, make_owner_token, settings):
    records = _records(upload, alice, 2)
    settings.CHECK_BUDGET = "3/day"
    client.force_login(alice.owner.user)
    assert client.get(reverse("record-detail", args=[records[0].pk])).status_code == 200
    assert session_client(alice.owner).get(SERIES, _series(alice)).status_code == 200
    # 3 checked: the API and every page that checks are refused now.
    _token, key = make_owner_token(alice.owner, scopes=("read",))
    assert _content(token_client(key), records[0]) == 429
    for name in ("record-detail", "record-raw"):
        page = client.get(reverse(name, args=[records[1].pk]))
        assert page.status_code == 429, name
        assert int(page["Retry-After"]) >= 1
        assert "no-store" in page["Cache-Control"]
    text = page.content.decode()
    assert "Too many requests" in text
    assert "integrity checks over budget" in text
    assert Verdict.objects.count() == 3


def test_a_page_that_checks_several_records_is_charged_all_of_them(client, alice, upload, settings):
    images = [
        upload(alice, seq, topic="/cam", data_type="sensor_msgs/Image", time=_iso(T0))
        for seq in range(1, 4)
    ]
    settings.CHECK_BUDGET = "2/day"
    client.force_login(alice.owner.user)
    gallery = client.get(reverse("record-gallery", args=[images[0].pk]))
    assert gallery.status_code == 429  # three images, two left
    assert not Verdict.objects.exists()


def test_two_callers_do_not_share_a_budget(alice, bob, upload, settings):
    _records(upload, alice, 2)
    settings.CHECK_BUDGET = "2/day"
    owner, grantee = session_client(alice.owner), session_client(bob)
    assert owner.get(SERIES, _series(alice)).status_code == 200
    assert owner.get(SERIES, _series(alice)).status_code == 429
    answer = grantee.get(SERIES, _series(alice))
    assert (answer.status_code, answer.json()["verified"]) == (200, 2)
    assert grantee.get(SERIES, _series(alice)).status_code == 429


def test_an_owner_token_spends_its_owners_budget(alice, upload, make_owner_token, settings):
    records = _records(upload, alice, 2)
    settings.CHECK_BUDGET = "2/day"
    _first, first_key = make_owner_token(alice.owner, scopes=("read",))
    _second, second_key = make_owner_token(alice.owner, scopes=("read",))
    assert token_client(first_key).get(SERIES, _series(alice)).status_code == 200
    # A second token of the same owner, and the owner's own session, find nothing left.
    assert _content(token_client(second_key), records[0]) == 429
    assert _content(session_client(alice.owner), records[0]) == 429


def test_a_batch_whose_read_stopped_waiting_is_not_checked_and_given_back(alice, upload, settings):
    records = _records(upload, alice, 3)
    settings.CHECK_BUDGET = "3/day"
    with check_run(caller_id=alice.owner.pk, records=3) as run:
        ended = run.id
    # The worker receives the batch after its read gave up: it checks nothing.
    ids = [str(record.pk) for record in records]
    assert tasks.records_verify(ids, alice.owner.pk, "session", None, None, "plot", ended) == []
    assert not Verdict.objects.exists()
    # The 3 records charged came back: all 3 fit again.
    answer = session_client(alice.owner).get(SERIES, _series(alice))
    assert (answer.status_code, answer.json()["verified"]) == (200, 3)


def test_reads_are_checked_uncounted_without_a_budget(alice, upload, settings):
    records = _records(upload, alice, 2)
    settings.CHECK_BUDGET = ""
    owner = session_client(alice.owner)
    assert [_content(owner, record) for record in records * 3] == [200] * 6


def test_reads_are_checked_uncounted_when_redis_cannot_count(alice, upload, settings, monkeypatch):
    record = upload(alice, 1, plaintext=odometry("alice", 0.0, 0.0))
    settings.CHECK_BUDGET = "1/day"
    down = redis_nobody_answers()
    monkeypatch.setattr("sharing.verification.budget.get_redis", lambda: down)
    owner = session_client(alice.owner)
    assert [_content(owner, record) for _ in range(3)] == [200, 200, 200]
