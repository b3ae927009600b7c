"""Bounded work on pages (F8): a plot is one batched integrity check (batches sent side by side
for a long one) with its verdicts written in one INSERT, and every owner page has a rate limit
per user (429 past it)."""

import re
from datetime import timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from sharing.models import Access, Verdict
from sharing.verification import opening
from stack.anvil import free_port
from tests.pages.conftest import odometry
from tests.support.redis_down import redis_nobody_answers
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

SERIES = "/api/v1/records/series/"


@pytest.fixture
def sent(monkeypatch):
    """The names of the tasks the web process sends for integrity checks."""
    names: list[str] = []
    real_dispatch = opening.dispatch

    def counting(task_name, *args, **kwargs):
        names.append(task_name)
        return real_dispatch(task_name, *args, **kwargs)

    monkeypatch.setattr(opening, "dispatch", counting)
    return names


def _verdict_inserts(queries: CaptureQueriesContext) -> int:
    insert = re.compile(rf'INSERT INTO "?{Verdict._meta.db_table}"?')
    return sum(1 for query in queries.captured_queries if insert.match(query["sql"]))


# --- one batched check per plot -------------------------------------------------------------


def _series(record, **extra: object) -> dict[str, object]:
    return {
        "robot": str(record.robot_id),
        "topic": record.topic,
        "fields": "position.x,position.y",
        "since": (record.captured_at - timedelta(minutes=1)).isoformat(),
        "until": (record.captured_at + timedelta(minutes=1)).isoformat(),
        **extra,
    }


def test_a_plot_is_one_check_and_one_insert(client, alice, bob, upload, sent):
    records = [upload(alice, seq, plaintext=odometry("alice", seq, seq)) for seq in range(1, 7)]
    tamper(records[2])
    for viewer in (alice.owner, bob):
        client.force_login(viewer.user)
        sent.clear()
        before = Verdict.objects.count()
        with CaptureQueriesContext(connection) as queries:
            plot = client.get(SERIES, _series(records[-1]))
        body = plot.json()
        assert plot.status_code == 200
        assert sent == ["sharing.tasks.series_verify"]
        assert _verdict_inserts(queries) == 1
        assert Verdict.objects.count() == before + len(records)
        # The tampered pose is refused and left out; the others are plotted.
        assert (body["verified"], body["refused"]) == (5, 1)
        assert [point[1] for point in body["points"]] == [1.0, 2.0, 4.0, 5.0, 6.0]
        verdicts = Verdict.objects.filter(access__viewer=viewer).order_by("-pk")[: len(records)]
        assert {v.outcome for v in verdicts} == {"verified", "tampered"}
        # One chain head for the batch; a verdict never says a block before its record's.
        assert all(v.block_number >= v.record.block_number for v in verdicts)
        heads = {v.block_number for v in verdicts if v.block_number > v.record.block_number}
        assert len(heads) <= 1


def test_a_long_plot_is_sent_in_batches_side_by_side(client, alice, upload, sent, monkeypatch):
    records = [upload(alice, seq, plaintext=odometry("alice", seq, 0)) for seq in range(1, 6)]
    monkeypatch.setattr(opening, "SERIES_BATCH", 2)
    client.force_login(alice.owner.user)
    body = client.get(SERIES, _series(records[-1])).json()
    assert sent == ["sharing.tasks.series_verify"] * 3
    assert body["verified"] == 5
    # Still one line of the access log for the whole plot.
    assert list(Access.objects.values_list("kind", "count")) == [("plot", 5)]


def test_a_strangers_plot_checks_nothing_and_learns_nothing(
    client, alice, make_owner, upload, sent
):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    upload(alice, 2, plaintext=odometry("alice", 1, 1))
    stranger = make_owner("mallory")
    client.force_login(stranger.user)
    body = client.get(SERIES, _series(record)).json()
    assert (body["source_records"], body["points"]) == (0, [])
    assert sent == []
    assert not Verdict.objects.filter(access__viewer=stranger).exists()


def test_a_record_page_keeps_its_single_check(client, alice, upload, sent):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    client.force_login(alice.owner.user)
    assert client.get(reverse("record-detail", args=[record.id])).status_code == 200
    assert sent == ["sharing.tasks.records_verify"]


def test_an_unavailable_check_answers_503_for_the_plot(client, alice, upload, settings):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    settings.VERIFY_TIMEOUT = 5
    client.force_login(alice.owner.user)
    answer = client.get(SERIES, _series(record))
    assert answer.status_code == 503


# --- page rate limits -----------------------------------------------------------------------


def test_pages_that_check_content_draw_on_a_budget_per_user(client, alice, bob, upload, settings):
    settings.CHECK_BUDGET = "3/day"
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    client.force_login(alice.owner.user)
    for name in ("record-detail", "record-raw", "record-detail"):
        assert client.get(reverse(name, args=[record.id])).status_code == 200
    refused = client.get(reverse("record-detail", args=[record.id]))
    assert refused.status_code == 429
    assert 1 <= int(refused["Retry-After"]) <= 86400
    assert "Too many requests" in refused.content.decode()
    assert "no-store" in refused["Cache-Control"]
    assert client.get(reverse("record-raw", args=[record.id])).status_code == 429
    # Other pages, and other users, are not held back by alice's content views.
    assert client.get(reverse("records")).status_code == 200
    client.force_login(bob.user)
    assert client.get(reverse("record-detail", args=[record.id])).status_code == 200


def test_every_owner_page_has_a_rate_per_user(client, alice, settings):
    settings.PAGE_RATE_USER = "4/day"
    client.force_login(alice.owner.user)
    pages = ["dashboard", "records", "shared", "grants"]
    for name in pages:
        assert client.get(reverse(name)).status_code == 200, name
    for name in [*pages, "audit", "robots", "key-rotation", "registration-progress"]:
        refused = client.get(reverse(name))
        assert refused.status_code == 429, name
        assert "Retry-After" in refused


def test_pages_are_served_when_redis_cannot_count(client, alice, settings, monkeypatch):
    settings.PAGE_RATE_USER = "1/day"
    down = redis_nobody_answers()
    monkeypatch.setattr("accounts.decorators.get_redis", lambda: down)
    client.force_login(alice.owner.user)
    for _ in range(3):
        assert client.get(reverse("dashboard")).status_code == 200


def test_anonymous_requests_go_to_sign_in_uncounted(client, settings):
    settings.PAGE_RATE_USER = "1/day"
    for _ in range(3):
        assert client.get(reverse("records")).status_code == 302
