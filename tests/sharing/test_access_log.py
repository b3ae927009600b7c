"""The access log: who viewed an owner's records, when, the verdict and the credential; the
owner's own views of shared records; filters, pages, CSV and the API.

The views are made straight in the database (tests/support/access_log_data.py); the last
tests check that the real view paths (page, API, admin, trajectory) record the credential.
"""

import csv
import io

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from accounts.services.robots import robot_create
from sharing import access_log
from sharing.access_log import csv_cell
from sharing.models import Credential, Verdict
from sharing.selectors.access import (
    ACCESS_LOG_INCOMING,
    ACCESS_LOG_OUTGOING,
    access_list_access_log,
    access_list_filtered,
)
from tests.api.conftest import session_client, token_client
from tests.support.access_log_data import (
    CAROL_TOPIC,
    FORMULA_ROBOT,
    FORMULA_TOKEN,
    FORMULA_TOPIC,
    access_log_world,
    at,
    view,
)

PAGE = reverse("access-log")
CSV = reverse("access-log-csv")
# The owner's own views are listed only when asked for (issue 48): these tests count them.
MINE = {"mine": "on"}
API = "/api/v1/access-log/"


@pytest.fixture(autouse=True)
def fast_password_hashing(settings) -> None:
    """Four users a test; their password hashes are not under test."""
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]


@pytest.fixture
def world(db, fast_password_hashing):
    return access_log_world()


def _ids(verdicts) -> list[int]:
    return [verdict.pk for verdict in verdicts]


def test_an_owner_sees_every_view_of_their_records_and_nothing_else(world):
    incoming = access_list_access_log(world.alice, direction=ACCESS_LOG_INCOMING)
    assert _ids(incoming) == world.access_ids("a4", "a3", "a2", "a1", "old")
    carol = access_list_access_log(world.carol, direction=ACCESS_LOG_INCOMING)
    assert _ids(carol) == world.access_ids("c2", "c1")
    # Bob owns nothing: nobody viewed his records, and his views are his outgoing side.
    assert not access_list_access_log(world.bob, direction=ACCESS_LOG_INCOMING).exists()


def test_a_grantee_sees_their_own_views_of_shared_records_apart(world):
    # Refused (a revoked grant): the owner sees the attempt, the grantee nothing of the record.
    refused = view(world.records["odom"], world.bob, 6, outcome=Verdict.Outcome.NO_ACCESS)
    outgoing = access_list_access_log(world.bob, direction=ACCESS_LOG_OUTGOING)
    assert _ids(outgoing) == world.access_ids("c1", "a3", "a2")
    incoming = access_list_access_log(world.alice, direction=ACCESS_LOG_INCOMING)
    assert _ids(incoming)[0] == refused.access_id
    # An owner's views of their own records, and the operator's checks, are incoming only.
    assert not access_list_access_log(world.alice, direction=ACCESS_LOG_OUTGOING).exists()
    with pytest.raises(ValueError, match="direction"):
        access_list_access_log(world.alice, direction="sideways")


@pytest.mark.parametrize(
    ("filters", "expected"),
    [
        ({"viewer": "bob"}, ["a3", "a2"]),
        ({"viewer": "carol"}, []),  # carol viewed only her own record
        ({"topic": FORMULA_TOPIC}, ["a4", "a2"]),
        ({"topic": CAROL_TOPIC}, []),
        ({"verdict": "tampered"}, ["a3"]),
        ({"credential": "token"}, ["a2"]),
        ({"credential": "operator"}, ["a4"]),
        ({"since": at(1), "until": at(3)}, ["a3", "a2"]),  # half-open
        ({"since": at(2), "until": at(2)}, []),
        ({"viewer": "bob", "verdict": "verified"}, ["a2"]),
    ],
)
def test_filters(world, filters, expected):
    accesses = access_list_access_log(world.alice, direction=ACCESS_LOG_INCOMING)
    assert _ids(access_list_filtered(accesses, **filters)) == world.access_ids(*expected)
    # The API lists the very same lines, filtered alike.
    params = {
        name: value.isoformat() if hasattr(value, "isoformat") else value
        for name, value in filters.items()
    }
    answer = session_client(world.alice).get(API, params)
    assert answer.status_code == 200, answer.content
    assert [row["id"] for row in answer.json()["results"]] == world.access_ids(*expected)


def test_the_page_log_lists_accesses_of_each_side(world):
    refused = view(world.records["odom"], world.bob, 6, outcome=Verdict.Outcome.NO_ACCESS)
    incoming = access_list_access_log(world.alice, direction=ACCESS_LOG_INCOMING)
    assert _ids(incoming) == [refused.access_id, *world.access_ids("a4", "a3", "a2", "a1", "old")]
    outgoing = access_list_access_log(world.bob, direction=ACCESS_LOG_OUTGOING)
    assert _ids(outgoing) == world.access_ids("c1", "a3", "a2")
    assert not access_list_access_log(world.alice, direction=ACCESS_LOG_OUTGOING).exists()


def test_filters_by_robot_and_by_owner(world):
    incoming = access_list_access_log(world.alice, direction=ACCESS_LOG_INCOMING)
    by_robot = access_list_filtered(incoming, robot=world.arm.pk)
    assert _ids(by_robot) == world.access_ids("a3", "a1", "old")
    outgoing = access_list_access_log(world.bob, direction=ACCESS_LOG_OUTGOING)
    assert _ids(access_list_filtered(outgoing, owner="carol")) == world.access_ids("c1")
    assert _ids(access_list_filtered(outgoing, owner="alice")) == world.access_ids("a3", "a2")


def test_the_page_lists_who_when_which_record_verdict_and_credential(client, world):
    client.force_login(world.alice.user)
    html = client.get(PAGE, MINE).content.decode()
    assert html.count('data-testid="access-log-row"') == 5
    # Bob's token, as alice may know it: a token, not its name or prefix (bob's business).
    assert 'data-testid="access-log-credential">owner API token</td>' in html
    assert world.token.token_prefix not in html
    assert "calc" not in html
    assert "operator check in the admin (operator)" in html
    assert "browser session" in html
    assert "not recorded" in html
    assert "TAMPERED" in html
    assert FORMULA_TOPIC in html
    assert "/odom" in html
    # Carol's record and her views never reach alice's page.
    assert CAROL_TOPIC not in html
    assert 'href="/access-log/"' in client.get(reverse("dashboard")).content.decode()
    filtered = client.get(PAGE, {"viewer": "bob", "verdict": "tampered"}).content.decode()
    assert filtered.count('data-testid="access-log-row"') == 1
    assert "1 access matches these filters" in filtered


def test_the_outgoing_tab_shows_my_views_with_whose_record(client, world):
    client.force_login(world.bob.user)
    html = client.get(PAGE, {"direction": "outgoing"}).content.decode()
    assert html.count('data-testid="access-log-row"') == 3
    assert CAROL_TOPIC in html
    owners = html.count('data-testid="access-log-owner">alice<') + html.count(
        'data-testid="access-log-owner">carol<'
    )
    assert owners == 3
    assert "owner API token “+cmd|&#x27; /C calc&#x27;!A0” (aro_" in html
    # Bob's own data: nobody viewed it.
    assert "Nobody has viewed your records yet." in client.get(PAGE).content.decode()


def test_the_page_costs_the_same_queries_for_2_or_60_rows_and_numbers_its_pages(client, world):
    client.force_login(world.alice.user)
    client.get(PAGE, MINE)  # the first request of a session writes more (the session itself)
    with CaptureQueriesContext(connection) as few:
        assert client.get(PAGE, MINE).status_code == 200
    for minute in range(60):
        view(world.records["camera"], world.bob, 10 + minute)
    with CaptureQueriesContext(connection) as many:
        page = client.get(PAGE, MINE)
    assert len(many) == len(few)
    html = page.content.decode()
    assert html.count('data-testid="access-log-row"') == 50
    assert 'data-testid="page-number">2<' in html
    second = client.get(PAGE, {**MINE, "page": "2"}).content.decode()
    assert second.count('data-testid="access-log-row"') == 15
    # Page numbers past the end or not numbers give a page, not an error.
    for junk in ("99", "abc", "-1", "1e9"):
        assert client.get(PAGE, {**MINE, "page": junk}).status_code == 200


BAD_FILTERS = [
    {"robot": "not-a-robot"},
    {"robot": "00000000-0000-0000-0000-000000000000"},  # nobody's robot: not offered
    {"verdict": "fine"},
    {"credential": "password"},
    {"since": "yesterday"},
    {"since": "2026-03-02T00:00", "until": "2026-03-01T00:00"},
    {"direction": "sideways"},
    {"topic": "a\x00b"},
    {"viewer": "x" * 151},
]


@pytest.mark.parametrize("params", BAD_FILTERS)
def test_bad_filters_are_left_out_with_a_message_never_a_500(client, world, params):
    """The page lists the log without the filter it names as left out; the CSV, which has
    no room to say so, is the page with the message (400) rather than another selection."""
    client.force_login(world.alice.user)
    # The one that does not hold (of a range, its end: the start holds alone).
    dropped = "until" if {"since", "until"} <= params.keys() else next(iter(params))
    held = {name: value for name, value in params.items() if name != dropped}
    expected = client.get(PAGE, held).content.decode().count('data-testid="access-log-row"')
    answer = client.get(PAGE, params)
    html = answer.content.decode()
    assert answer.status_code == 200, params
    assert 'class="errorlist' in html
    assert "Left out of the filters" in html
    assert html.count('data-testid="access-log-row"') == expected, params
    assert 'data-testid="access-log-csv"' not in html
    download = client.get(CSV, params)
    assert download.status_code == 400, params
    assert "No download: Left out of the filters" in download.content.decode()


@pytest.mark.parametrize("params", [*BAD_FILTERS, {"limit": "0"}, {"offset": "x"}])
def test_bad_filters_are_a_400_in_the_api(world, params):
    answer = session_client(world.alice).get(API, params)
    if params.get("robot") == "00000000-0000-0000-0000-000000000000":
        # The API takes any robot id, as the records API does: nobody's robot lists nothing.
        assert answer.status_code == 200
        assert answer.json()["count"] == 0
        return
    assert answer.status_code == 400, (params, answer.content)
    assert answer.json()["error"] == "invalid_request"


def _csv_rows(response) -> list[dict[str, str]]:
    assert response.streaming
    assert response["Content-Type"] == "text/csv; charset=utf-8"
    assert response["Content-Disposition"].startswith('attachment; filename="access-log-')
    text = b"".join(response.streaming_content).decode()
    return list(csv.DictReader(io.StringIO(text)))


def test_the_csv_holds_the_filtered_rows_with_no_formula_cell(client, world):
    client.force_login(world.alice.user)
    rows = _csv_rows(client.get(CSV, MINE))
    assert [int(row["records"]) for row in rows] == [1] * 5
    assert [row["kind"] for row in rows] == ["check", "view", "view", "view", "view"]
    assert [row["viewer"] for row in rows] == ["alice", "bob", "bob", "alice", "alice"]
    token_row = rows[2]
    assert token_row["credential"] == "token"
    assert token_row["token_name"] == token_row["token_prefix"] == ""  # bob's business
    assert token_row["robot"] == "'" + FORMULA_ROBOT
    assert token_row["topic"] == "'" + FORMULA_TOPIC
    assert token_row["record"] == str(world.records["camera"].pk)
    assert rows[0]["credential"] == "operator"
    assert rows[0]["operator"] == "operator"
    assert rows[-1]["credential"] == "not_recorded"
    for row in rows:
        assert not any(cell.startswith(("=", "+", "-", "@")) for cell in row.values()), row
    assert CAROL_TOPIC not in str(rows)
    # The page's filters apply to the download.
    only = _csv_rows(client.get(CSV, {"viewer": "bob", "credential": "session"}))
    assert [row["verdict"] for row in only] == ["tampered"]
    # Bob's own download names his token, neutralised.
    client.force_login(world.bob.user)
    mine = _csv_rows(client.get(CSV, {"direction": "outgoing", "credential": "token"}))
    assert [(row["token_name"], row["token_prefix"]) for row in mine] == [
        ("'" + FORMULA_TOKEN, world.token.token_prefix)
    ]


def test_the_csv_reads_in_chunks_and_loses_no_row_at_equal_times(client, world, monkeypatch):
    monkeypatch.setattr(access_log, "CSV_CHUNK", 2)
    for _ in range(4):  # four views at the very same time as a2
        view(world.records["camera"], world.bob, 1)
    client.force_login(world.alice.user)
    with CaptureQueriesContext(connection) as queries:
        rows = _csv_rows(client.get(CSV, MINE))
    assert len(rows) == 9
    assert len({row["id"] for row in rows}) == 9
    # 9 rows in chunks of 2: 5 reads of the log (and a few for the session and choices).
    log_reads = [q for q in queries.captured_queries if 'FROM "sharing_access"' in q["sql"]]
    assert len(log_reads) == 5


@pytest.mark.parametrize(
    ("value", "cell"),
    [
        ("=1+1", "'=1+1"),
        ("+1", "'+1"),
        ("-1", "'-1"),
        ("@A1", "'@A1"),
        ("\t=1", "'\t=1"),
        ("/odom", "/odom"),
        (None, ""),
        (7, "7"),
    ],
)
def test_csv_cells_never_start_a_formula(value, cell):
    assert csv_cell(value) == cell


def test_the_api_lists_the_same_log_for_an_owner_token_with_read(world, make_owner_token):
    _, key = make_owner_token(world.alice, scopes=("read",))
    answer = token_client(key).get(API, {"viewer": "bob"})
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert body["count"] == 2
    entry = body["results"][1]
    assert entry["id"] == world.views["a2"].access_id
    assert (entry["kind"], entry["records"], entry["block_number"]) == ("view", 1, 7)
    assert entry["credential"] == "token"
    assert entry["token"] is None  # bob's token: its name and prefix are his
    assert entry["operator"] is None
    assert entry["record"] == str(world.records["camera"].pk)
    assert entry["robot_name"] == FORMULA_ROBOT
    assert entry["verdict"] == "verified"
    old = token_client(key).get(API, {"until": "2026-03-01T00:00Z"}).json()["results"]
    assert [(row["id"], row["credential"]) for row in old] == [(world.views["old"].access_id, None)]
    # Bob's outgoing side, with his session.
    outgoing = session_client(world.bob).get(API, {"direction": "outgoing", "owner": "carol"})
    assert [row["id"] for row in outgoing.json()["results"]] == world.access_ids("c1")
    mine = session_client(world.bob).get(API, {"direction": "outgoing", "credential": "token"})
    assert [row["token"] for row in mine.json()["results"]] == [
        {"name": FORMULA_TOKEN, "prefix": world.token.token_prefix}
    ]


def test_the_api_needs_the_read_scope_and_never_a_robot(world, make_owner_token):
    _, share_only = make_owner_token(world.alice, scopes=("share",))
    answer = token_client(share_only).get(API)
    assert answer.status_code == 403
    assert answer.json()["error"] == "insufficient_scope"
    _, robot_token = robot_create(owner=world.alice, name="scout")
    assert token_client(robot_token).get(API).status_code == 403
    assert token_client("").get(API).status_code == 401


# --- the view paths record the credential -------------------------------------------------------


def test_views_record_their_credential(
    alice, bob, upload, client, make_owner_token, django_user_model
):
    from sharing.verification.check import records_verify

    record = upload(alice, 1)
    second = upload(alice, 2)
    client.force_login(alice.owner.user)
    assert client.get(reverse("record-detail", args=[record.pk])).status_code == 200
    token, key = make_owner_token(bob, scopes=("read",))
    content = token_client(key).get(f"/api/v1/records/{record.pk}/content/")
    assert content.status_code == 200, content.content
    assert session_client(bob).get(f"/api/v1/records/{second.pk}/content/").status_code == 200
    operator = django_user_model.objects.create_user(username="op", is_staff=True)
    records_verify(record_ids=[record.pk], viewer_id=alice.owner.pk, checked_by_id=operator.pk)[0]
    records_verify(
        record_ids=[record.pk, second.pk],
        viewer_id=bob.pk,
        credential=Credential.TOKEN,
        token_id=token.pk,
    )
    made = list(
        Verdict.objects.order_by("id").values_list(
            "access__viewer_id",
            "access__record_owner_id",
            "access__credential",
            "access__token_id",
            "access__checked_by_id",
        )
    )
    a, b = alice.owner.pk, bob.pk
    assert made == [
        (a, a, "session", None, None),
        (b, a, "token", token.pk, None),
        (b, a, "session", None, None),
        (a, a, "operator", None, operator.pk),
        (b, a, "token", token.pk, None),
        (b, a, "token", token.pk, None),
    ]
    with pytest.raises(ValueError, match="token"):
        records_verify(record_ids=[record.pk], viewer_id=b, credential=Credential.TOKEN)[0]
    assert Verdict.objects.count() == len(made)
    # And the owner's log lists all of them, one line per read (the last two records were
    # one read); bob's outgoing side his own.
    log = access_list_access_log(alice.owner, direction=ACCESS_LOG_INCOMING)
    assert log.count() == len(made) - 1
    assert access_list_access_log(bob, direction=ACCESS_LOG_OUTGOING).count() == 3
