"""The series API as plots ask for it (GET /api/v1/records/series/, sharing/thinning.py): a path
thinned along x-y with each point one checked record's, a time plot by per-field extremes, the
`method` said; a bad shape a clear 400 that writes nothing; a refresh (`after`) reads and
checks only the newer records and adds them to the caller's one access line of the plot."""

import math
from datetime import UTC, datetime, timedelta

import pytest
from django.utils import timezone

from sharing.models import Access, Record, Verdict
from sharing.services.uploads import record_create_batch
from sharing.verification.access import PLOT_REFRESHES_COALESCED
from stack.anvil import free_port
from tests.api.conftest import session_client, token_client
from tests.pages.conftest import odometry

pytestmark = pytest.mark.django_db

API = "/api/v1/records/series/"
ODOM = "/robot/odom"
T0 = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(minutes=30)


def _iso(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


def _figure_eight(i: int) -> tuple[float, float]:
    a = 2 * math.pi * i / 100
    return round(3 * math.sin(a), 6), round(3 * math.sin(a) * math.cos(a), 6)


@pytest.fixture
def drive(django_capture_on_commit_callbacks):
    """Upload records `first..last-1` of a figure-8 at 10 Hz from T0, one upload, anchored."""

    def upload(setup, first: int, last: int) -> list[Record]:
        envelopes = [
            setup.seal(
                i + 1,
                plaintext=odometry(setup.owner.username, *_figure_eight(i)),
                time=_iso(T0 + timedelta(seconds=i / 10)),
            )
            for i in range(first, last)
        ]
        with django_capture_on_commit_callbacks(execute=True):
            records = record_create_batch(robot=setup.robot, envelopes=envelopes)
        return records

    return upload


def _query(setup, **extra: object) -> dict[str, object]:
    return {
        "robot": str(setup.robot.pk),
        "topic": ODOM,
        "fields": "position.x,position.y",
        "since": _iso(T0),
        "until": _iso(T0 + timedelta(minutes=5)),
        **extra,
    }


def _driven(count: int) -> list[list[float]]:
    """The rows [t, x, y] of the records drive() uploaded, as the series answers them."""
    return [[(T0 + timedelta(seconds=i / 10)).timestamp(), *_figure_eight(i)] for i in range(count)]


def test_a_path_is_thinned_along_it_each_point_one_checked_record(alice, drive):
    drive(alice, 0, 300)
    client = session_client(alice.owner)
    answer = client.get(API, _query(alice, shape="path", points=40))
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert (body["shape"], body["method"]) == ("path", "largest-triangle-three-buckets")
    assert (body["source_records"], body["verified"]) == (300, 300)
    rows = _driven(300)
    assert len(body["points"]) == 40
    assert all(point in rows for point in body["points"])  # t, x and y of one record
    assert (body["points"][0], body["points"][-1]) == (rows[0], rows[-1])
    assert body["points"] == sorted(body["points"])
    # Each field over time: per-bucket extremes, each a record's too.
    body = client.get(API, _query(alice, shape="time", points=40)).json()
    assert (body["shape"], body["method"]) == ("time", "min-max-per-time-bucket")
    assert len(body["points"]) <= 40
    assert all(point in rows for point in body["points"])
    # Under the limit, every record; without a shape, the time plot's.
    body = client.get(API, _query(alice, points=1000)).json()
    assert (body["shape"], body["method"], body["points"]) == ("time", "all", rows)


@pytest.mark.parametrize(
    ("extra", "code", "words"),
    [
        ({"shape": "diamond"}, "invalid_request", "shape is `time` or `path`"),
        ({"shape": "path", "fields": "position.x"}, "invalid_series", "a path plots two fields"),
        ({"after": "soon"}, "invalid_request", "number"),
        ({"after": "1764380000.1234567"}, "invalid_request", "decimal places"),
        ({"after": "-1"}, "invalid_request", "greater than or equal"),
    ],
)
def test_a_bad_shape_or_after_is_a_clear_400_and_writes_nothing(alice, drive, extra, code, words):
    drive(alice, 0, 5)
    answer = session_client(alice.owner).get(API, _query(alice, **extra))
    assert answer.status_code == 400, answer.content
    body = answer.json()
    assert body["error"] == code, body
    assert words in str(body), body
    assert not Access.objects.exists()
    assert not Verdict.objects.exists()


def test_after_the_end_of_the_range_is_a_clear_400(alice, drive):
    drive(alice, 0, 5)
    until = T0 + timedelta(minutes=5)
    answer = session_client(alice.owner).get(API, _query(alice, after=str(until.timestamp())))
    assert answer.status_code == 400, answer.content
    assert answer.json()["error"] == "invalid_series"
    assert "after must be before until" in str(answer.json())
    assert not Access.objects.exists()


def test_a_refresh_checks_only_the_newer_records_and_adds_to_the_plots_one_line(alice, drive):
    drive(alice, 0, 50)
    client = session_client(alice.owner)
    first = client.get(API, _query(alice, shape="path")).json()
    assert len(first["points"]) == 50
    (line,) = Access.objects.filter(viewer=alice.owner)
    assert (line.kind, line.count) == ("plot", 50)

    drive(alice, 50, 57)  # newer records arrive
    newest = first["points"][-1][0]
    refresh = client.get(API, _query(alice, shape="path", after=str(newest)))
    assert refresh.status_code == 200, refresh.content
    body = refresh.json()
    # Only the 7 newer records were read and checked, and answered.
    assert (body["source_records"], body["verified"]) == (7, 7)
    assert body["points"] == _driven(57)[50:]
    # Nothing new: nothing read, nothing logged.
    empty = client.get(API, _query(alice, shape="path", after=str(body["points"][-1][0])))
    assert empty.json()["source_records"] == 0

    # Still one line in the access log, naming all it read; a verdict per record checked.
    (line,) = Access.objects.filter(viewer=alice.owner)
    assert (line.kind, line.count, line.record_id) == ("plot", 57, None)
    assert line.verdicts.count() == 57
    assert sorted(v.record.seq for v in line.verdicts.all())[-7:] == list(range(51, 58))


def test_a_refresh_begins_a_new_line_after_the_window_or_with_another_credential(
    alice, drive, make_owner_token
):
    drive(alice, 0, 10)
    client = session_client(alice.owner)
    client.get(API, _query(alice))
    Access.objects.update(
        created_at=timezone.now() - PLOT_REFRESHES_COALESCED - timedelta(seconds=1)
    )
    drive(alice, 10, 12)
    after = str(_driven(10)[-1][0])
    assert client.get(API, _query(alice, after=after)).json()["verified"] == 2
    # An API token's refresh is its own line, not the session's.
    _token, key = make_owner_token(alice.owner, scopes=("read",))
    assert token_client(key).get(API, _query(alice, after=after)).json()["verified"] == 2
    lines = Access.objects.filter(viewer=alice.owner).order_by("created_at", "id")
    assert [(line.count, line.credential) for line in lines] == [
        (10, "session"),
        (2, "session"),
        (2, "token"),
    ]
    # A plot asked whole (no `after`) is its own line, never added to one.
    client.get(API, _query(alice))
    assert Access.objects.filter(viewer=alice.owner).count() == 4


def test_a_refresh_no_check_answered_leaves_the_plots_line_as_it_was(alice, drive, settings):
    drive(alice, 0, 10)
    client = session_client(alice.owner)
    client.get(API, _query(alice))
    drive(alice, 10, 13)
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"  # the check cannot run
    settings.VERIFY_TIMEOUT = 5
    answer = client.get(API, _query(alice, after=str(_driven(10)[-1][0])))
    assert answer.status_code == 503
    assert answer.json()["error"] == "verification_unavailable"
    (line,) = Access.objects.filter(viewer=alice.owner)
    assert (line.count, line.verdicts.count()) == (10, 10)


def test_a_record_read_again_by_a_refresh_is_one_record_of_the_line(
    alice, django_capture_on_commit_callbacks
):
    client = session_client(alice.owner)
    envelopes = [
        alice.seal(
            i + 1,
            plaintext=odometry(alice.owner.username, *_figure_eight(i)),
            time=_iso(T0 + timedelta(seconds=i / 10)),
        )
        for i in range(8)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=alice.robot, envelopes=envelopes[:5])
    first = client.get(API, _query(alice)).json()
    newest = str(first["points"][-1][0])
    # Three newer records, not anchored yet: a refresh reads them and cannot draw them...
    with django_capture_on_commit_callbacks(execute=False) as anchoring:
        record_create_batch(robot=alice.robot, envelopes=envelopes[5:])
    pending = client.get(API, _query(alice, after=newest)).json()
    assert (pending["source_records"], pending["not_anchored_yet"]) == (3, 3)
    (line,) = Access.objects.filter(viewer=alice.owner)
    assert line.count == 8
    # ...so the next refresh asks for them again from the same point, anchored by then: each
    # is checked again (a verdict each time), and the line still counts 8 records, not 11.
    for callback in anchoring:
        callback()
    again = client.get(API, _query(alice, after=newest)).json()
    assert (again["source_records"], again["verified"]) == (3, 3)
    (line,) = Access.objects.filter(viewer=alice.owner)
    assert (line.count, line.verdicts.count()) == (8, 11)
