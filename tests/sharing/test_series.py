"""Series (sharing/series.py, GET /api/v1/records/series/): every record in range checked through
the one check path, refused ones counted and never plotted, shape-keeping downsampling, bounded
parameters, the grant's scope, and one access-log line of kind "plot" with its credential."""

import re
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from chainworker.client import AuthROSChain
from sharing.grant_terms import grant_terms_make
from sharing.models import Access, Record, Verdict
from sharing.series import field_value
from sharing.services.grants import grant_create
from sharing.verification.check import records_verify
from tests.api.conftest import session_client, token_client
from tests.pages.conftest import image, odometry
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

API = "/api/v1/records/series/"
ODOM = "/robot/odom"
T0 = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(minutes=30)


def _iso(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


def _odometry(upload, setup, seq: int, *, x: float, y: float, at: datetime) -> Record:
    plaintext = odometry(setup.owner.username, x, y)
    return upload(setup, seq, plaintext=plaintext, time=_iso(at))


def _query(setup, *, since: datetime, until: datetime, **extra: object) -> dict[str, object]:
    return {
        "robot": str(setup.robot.pk),
        "topic": ODOM,
        "fields": "position.x,position.y",
        "since": _iso(since),
        "until": _iso(until),
        **extra,
    }


def test_the_series_answers_every_record_in_range_and_refuses_a_tampered_one(alice, upload):
    records = [
        _odometry(upload, alice, i + 1, x=float(i), y=2.0 * i, at=T0 + timedelta(seconds=i))
        for i in range(8)
    ]
    _odometry(upload, alice, 9, x=99.0, y=99.0, at=T0 + timedelta(minutes=5))  # out of range
    tamper(records[3])
    answer = session_client(alice.owner).get(
        API, _query(alice, since=T0, until=T0 + timedelta(minutes=1))
    )
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert body["fields"] == ["position.x", "position.y"]
    assert (body["source_records"], body["verified"], body["refused"]) == (8, 7, 1)
    expected = [
        [(T0 + timedelta(seconds=i)).timestamp(), float(i), 2.0 * i] for i in range(8) if i != 3
    ]
    assert body["points"] == expected  # the tampered record's (3, 6) is never plotted
    # One access-log line for the whole plot, with the browser session; a verdict per record.
    (access,) = Access.objects.filter(viewer=alice.owner)
    assert (access.kind, access.count, access.credential) == ("plot", 8, "session")
    assert access.topic == ODOM
    assert access.robot_id == alice.robot.pk
    outcomes = sorted(access.verdicts.values_list("outcome", flat=True))
    assert outcomes == ["tampered"] + ["verified"] * 7


def test_records_not_anchored_yet_are_counted_apart_from_the_refused(alice, upload):
    for i in range(3):
        _odometry(upload, alice, i + 1, x=float(i), y=0.0, at=T0 + timedelta(seconds=i))
    tampered = _odometry(upload, alice, 4, x=4.0, y=0.0, at=T0 + timedelta(seconds=4))
    tamper(tampered)
    for i in (5, 6):  # their anchoring has not run
        plaintext = odometry(alice.owner.username, float(i), 0.0)
        at = _iso(T0 + timedelta(seconds=i))
        upload(alice, i, plaintext=plaintext, time=at, anchor=False)
    body = (
        session_client(alice.owner)
        .get(API, _query(alice, since=T0, until=T0 + timedelta(minutes=1)))
        .json()
    )
    counts = ("source_records", "verified", "refused", "not_anchored_yet")
    assert tuple(body[name] for name in counts) == (6, 3, 1, 2)
    assert [point[1] for point in body["points"]] == [0.0, 1.0, 2.0]


def test_a_series_with_an_owner_token_is_logged_as_that_token(alice, upload, make_owner_token):
    _odometry(upload, alice, 1, x=1.0, y=1.0, at=T0)
    token, key = make_owner_token(alice.owner, scopes=("read",))
    query = _query(alice, since=T0, until=T0 + timedelta(minutes=1))
    answer = token_client(key).get(API, query)
    assert answer.status_code == 200, answer.content
    assert answer.json()["verified"] == 1
    access = Access.objects.get(viewer=alice.owner)
    assert (access.kind, access.credential, access.token_id) == ("plot", "token", token.pk)
    # Without the read scope, or with a robot's token: refused, nothing checked.
    _other, share_only = make_owner_token(alice.owner, scopes=("share",))
    assert token_client(share_only).get(API, query).status_code == 403
    assert token_client(alice.token).get(API, query).status_code == 403
    assert Access.objects.count() == 1


def _bad(alice) -> list[dict[str, object]]:
    since, until = T0, T0 + timedelta(minutes=1)
    good = _query(alice, since=since, until=until)
    return [
        {key: value for key, value in good.items() if key != "fields"},
        {key: value for key, value in good.items() if key != "since"},
        {**good, "fields": ""},
        {**good, "fields": ",".join(f"f{i}" for i in range(9))},
        {**good, "fields": "position..x"},
        {**good, "fields": "position.x;drop"},
        {**good, "fields": "a" * 300},
        {**good, "points": "1"},
        {**good, "points": "1000000"},
        {**good, "points": "many"},
        {**good, "robot": "not-a-robot"},
        {**good, "since": _iso(until), "until": _iso(since)},
        {**good, "since": "yesterday"},
        {**good, "until": _iso(since + timedelta(days=30))},
        {**good, "topic": "a\x00b"},
    ]


def test_bad_parameters_are_a_clear_400_and_change_nothing(alice, upload):
    _odometry(upload, alice, 1, x=1.0, y=1.0, at=T0)
    client = session_client(alice.owner)
    verdicts = Verdict.objects.count()
    for params in _bad(alice):
        answer = client.get(API, params)
        assert answer.status_code == 400, (params, answer.content)
        assert answer.json()["error"] in ("invalid_request", "invalid_series"), params
        assert answer.json()["detail"], params
    assert Verdict.objects.count() == verdicts
    assert not Access.objects.exists()


def test_a_range_holding_more_records_than_allowed_is_refused(alice, upload, settings):
    for i in range(3):
        _odometry(upload, alice, i + 1, x=1.0, y=1.0, at=T0 + timedelta(seconds=i))
    settings.SERIES_MAX_RECORDS = 2
    answer = session_client(alice.owner).get(
        API, _query(alice, since=T0, until=T0 + timedelta(minutes=1))
    )
    assert answer.status_code == 400
    assert "more than 2 records" in answer.json()["detail"]
    assert not Access.objects.exists()


def test_any_numeric_field_of_any_json_record_over_time(alice, upload):
    plaintext = b'{"K": {"battery": {"cells": [3.7, 3.6]}, "ok": true, "name": "x"}}'
    upload(alice, 1, plaintext=plaintext, topic="/battery", data_type="x/Battery", time=_iso(T0))
    query = {
        **_query(alice, since=T0, until=T0 + timedelta(minutes=1)),
        "topic": "/battery",
        "fields": "battery.cells.1,ok,name,missing.path",
    }
    body = session_client(alice.owner).get(API, query).json()
    assert body["points"] == [[T0.timestamp(), 3.6, None, None, None]]


def test_scope_limits_the_plot_and_the_gallery_to_what_the_grant_covers(
    alice, make_owner, upload, make_robot, django_capture_on_commit_callbacks
):
    from accounts.services.robots import robot_create

    other_robot, _token = robot_create(owner=alice.owner, name="other")
    inside = [
        _odometry(upload, alice, i + 1, x=float(i), y=0.0, at=T0 + timedelta(seconds=10 * i))
        for i in range(4)
    ]
    # Alice's other robot, same topic, same time: not in bob's grant.
    other = alice.__class__(alice.owner, alice.key, other_robot, "", None)
    upload(other, 1, plaintext=odometry("alice", 50.0, 50.0), time=_iso(T0 + timedelta(seconds=5)))
    bob = make_owner("bob")
    terms = grant_terms_make(
        owner=alice.owner,
        robots=[alice.robot.pk],
        since=T0,
        until=T0 + timedelta(seconds=25),  # inside[0..2]
    )
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob, terms=terms)
    client = session_client(bob)
    body = client.get(API, _query(alice, since=T0, until=T0 + timedelta(minutes=1))).json()
    assert (body["source_records"], body["verified"], body["refused"]) == (3, 3, 0)
    assert [point[1] for point in body["points"]] == [0.0, 1.0, 2.0]
    assert Access.objects.get(viewer=bob).count == 3
    outside = client.get(API, _query(other, since=T0, until=T0 + timedelta(minutes=1))).json()
    assert outside["source_records"] == 0
    assert outside["points"] == []
    assert not Verdict.objects.filter(access__viewer=bob, record__robot=other_robot).exists()
    assert inside[3].pk not in set(
        Verdict.objects.filter(access__viewer=bob).values_list("record", flat=True)
    )


def test_the_gallery_of_a_scoped_grant_lists_only_records_in_scope(
    alice, make_owner, upload, django_capture_on_commit_callbacks
):
    from accounts.services.robots import robot_create

    topic, kind = "/robot/complicatedImage", "sensor_msgs/Image"
    shots = [
        upload(
            alice,
            i + 1,
            plaintext=image("alice"),
            topic=topic,
            data_type=kind,
            time=_iso(T0 + timedelta(seconds=10 * i)),
        )
        for i in range(4)
    ]
    other_robot, _token = robot_create(owner=alice.owner, name="other-camera")
    other = alice.__class__(alice.owner, alice.key, other_robot, "", None)
    foreign = upload(
        other,
        1,
        plaintext=image("alice"),
        topic=topic,
        data_type=kind,
        time=_iso(T0 + timedelta(seconds=5)),
    )
    bob = make_owner("bob")
    terms = grant_terms_make(
        owner=alice.owner, robots=[alice.robot.pk], since=T0, until=T0 + timedelta(seconds=25)
    )
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob, terms=terms)
    client = session_client(bob)
    window = {
        "since": (T0 - timedelta(minutes=2)).strftime("%Y-%m-%dT%H:%M"),
        "until": (T0 + timedelta(minutes=2)).strftime("%Y-%m-%dT%H:%M"),
    }
    html = client.get(reverse("record-gallery", args=[shots[0].pk]), window).content.decode()
    listed = re.findall(r'data-record-id="([0-9a-f-]+)"', html)
    assert listed == [str(shot.pk) for shot in shots[:3]]
    for hidden in (shots[3], foreign):
        assert str(hidden.pk) not in html
        assert hidden.captured_at.strftime("%H:%M:%S") not in html
    assert 'data-testid="gallery-refused"' not in html
    # One access-log line for the page: a page of 3 records, with the browser session.
    access = Access.objects.get(viewer=bob)
    assert (access.kind, access.count, access.credential) == ("page", 3, "session")
    assert access.verdicts.count() == 3


def test_the_check_asks_rootof_once_per_tree_and_writes_verdicts_in_one_insert(
    alice, upload, monkeypatch, django_capture_on_commit_callbacks
):
    # Two trees: three records anchored together, then two more together.
    first = [upload(alice, seq, anchor=False) for seq in (1, 2)]
    first.append(upload(alice, 3))
    second = [upload(alice, 4, anchor=False), upload(alice, 5)]
    records = first + second
    for record in records:
        record.refresh_from_db()
    trees = {record.anchor_root_id for record in records}
    assert len(trees) == 2
    asked: list[str] = []
    real_root_of = AuthROSChain.root_of

    def counting(self, sender, root):
        asked.append(root.hex())
        return real_root_of(self, sender, root)

    monkeypatch.setattr(AuthROSChain, "root_of", counting)
    with CaptureQueriesContext(connection) as queries:
        checked = records_verify(record_ids=[r.pk for r in records], viewer_id=alice.owner.pk)
    assert [c.verdict.outcome for c in checked] == ["verified"] * 5
    assert len(asked) == 2
    assert len(set(asked)) == 2
    inserts = [
        q for q in queries.captured_queries if q["sql"].startswith('INSERT INTO "sharing_verdict"')
    ]
    assert len(inserts) == 1
    # One Access for the run (a page of five), every verdict under it.
    access = Access.objects.get()
    assert (access.kind, access.count) == ("page", 5)
    assert {c.verdict.access_id for c in checked} == {access.pk}


def test_a_record_page_is_one_view_entry_with_its_session(alice, bob, upload, client):
    record = _odometry(upload, alice, 1, x=1.0, y=2.0, at=T0)
    client.force_login(bob.user)
    page = client.get(reverse("record-detail", args=[record.pk]))
    assert page.status_code == 200
    html = page.content.decode()
    # The trajectory is drawn by the series plot, from the API, around the record.
    assert "data-series-plot" in html
    assert 'data-fields="position.x,position.y"' in html
    assert f'data-robot="{alice.robot.pk}"' in html
    assert "series-plot.js" in html
    access = Access.objects.get(viewer=bob)
    assert (access.kind, access.count, access.credential, access.record_id) == (
        "view",
        1,
        "session",
        record.pk,
    )
    # Alice's access log says it: one line, a view by bob's browser session.
    client.force_login(alice.owner.user)
    log = client.get(reverse("access-log")).content.decode()
    assert log.count('data-testid="access-log-row"') == 1
    assert "browser session" in log
    assert "not recorded" not in log


def test_the_access_log_shows_a_plot_as_one_line_naming_its_records(alice, upload, client):
    for i in range(5):
        _odometry(upload, alice, i + 1, x=float(i), y=0.0, at=T0 + timedelta(seconds=i))
    query = _query(alice, since=T0, until=T0 + timedelta(minutes=1))
    assert session_client(alice.owner).get(API, query).status_code == 200
    client.force_login(alice.owner.user)
    log = client.get(reverse("access-log"), {"mine": "on"}).content.decode()  # its own view
    assert log.count('data-testid="access-log-row"') == 1
    assert 'data-kind="plot" data-count="5"' in log
    assert "plot, 5 records" in log
    assert "5 verified" in log
    assert "browser session" in log


# --- pure parts ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("document", "path", "value"),
    [
        ({"a": {"b": 1.5}}, "a.b", 1.5),
        ({"a": [1, 2, 3]}, "a.2", 3.0),
        ({"a": [1]}, "a.5", None),
        ({"a": True}, "a", None),
        ({"a": "1"}, "a", None),
        ({"a": 10**40}, "a", None),
        ({"a": {"b": None}}, "a.b", None),
        ([1, 2], "0", 1.0),
        ("text", "a", None),
    ],
)
def test_field_value_reads_only_finite_bounded_numbers(document, path, value):
    assert field_value(document, path) == value
