"""Bounded work on pages (F8): a trajectory is one batched integrity check with its verdicts
written in one INSERT, and every owner page has a rate limit per user (429 past it)."""

import re

import pytest
import redis
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from sharing import verification
from sharing.models import Verdict
from sharing.views import TRAJECTORY_COST
from stack.anvil import free_port
from tests.conftest import tamper
from tests.pages.conftest import odometry

pytestmark = pytest.mark.django_db


@pytest.fixture
def sent(monkeypatch):
    """The names of the tasks the web process sends for integrity checks."""
    names: list[str] = []
    real_dispatch = verification.dispatch

    def counting(task_name, *args, **kwargs):
        names.append(task_name)
        return real_dispatch(task_name, *args, **kwargs)

    monkeypatch.setattr(verification, "dispatch", counting)
    return names


def _verdict_inserts(queries: CaptureQueriesContext) -> int:
    insert = re.compile(rf'INSERT INTO "?{Verdict._meta.db_table}"?')
    return sum(1 for query in queries.captured_queries if insert.match(query["sql"]))


# --- one batched check per trajectory -------------------------------------------------------


def test_a_trajectory_is_one_check_and_one_insert(client, alice, bob, upload, sent):
    records = [upload(alice, seq, plaintext=odometry("alice", seq, seq)) for seq in range(1, 7)]
    tamper(records[2])
    for viewer in (alice.owner, bob):
        client.force_login(viewer.user)
        sent.clear()
        before = Verdict.objects.count()
        with CaptureQueriesContext(connection) as queries:
            plot = client.get(reverse("record-trajectory", args=[records[-1].id]))
        svg = plot.content.decode()
        assert plot.status_code == 200
        assert sent == ["sharing.tasks.records_verify"]
        assert _verdict_inserts(queries) == 1
        assert Verdict.objects.count() == before + len(records)
        # The tampered pose is refused and left out; the others are plotted.
        assert "5 positions," in svg
        assert "1 record left out (not verified)" in svg
        verdicts = Verdict.objects.filter(viewer=viewer).order_by("-pk")[: len(records)]
        assert {v.outcome for v in verdicts} == {"verified", "tampered"}
        # One chain head for the batch; a verdict never says a block before its record's.
        assert all(v.block_number >= v.record.block_number for v in verdicts)
        heads = {v.block_number for v in verdicts if v.block_number > v.record.block_number}
        assert len(heads) <= 1


def test_a_trajectory_of_a_record_without_access_is_refused_in_its_one_check(
    client, alice, make_owner, upload, sent
):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    upload(alice, 2, plaintext=odometry("alice", 1, 1))
    stranger = make_owner("mallory")
    client.force_login(stranger.user)
    answer = client.get(reverse("record-trajectory", args=[record.id]))
    assert answer.status_code == 403
    assert sent == ["sharing.tasks.records_verify"]
    assert not Verdict.objects.filter(viewer=stranger).exclude(outcome="no_access").exists()


def test_a_record_page_keeps_its_single_check(client, alice, upload, sent):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    client.force_login(alice.owner.user)
    assert client.get(reverse("record-detail", args=[record.id])).status_code == 200
    assert sent == ["sharing.tasks.record_verify"]


def test_an_unavailable_batch_refuses_every_pose(client, alice, upload, settings):
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    settings.VERIFY_TIMEOUT = 5
    client.force_login(alice.owner.user)
    answer = client.get(reverse("record-trajectory", args=[record.id]))
    assert answer.status_code == 503


# --- page rate limits -----------------------------------------------------------------------


def test_pages_that_check_content_have_a_rate_per_user(client, alice, bob, upload, settings):
    settings.PAGE_RATE_CONTENT = "3/day"
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


def test_a_trajectory_costs_more_than_one_view(client, alice, upload, settings):
    settings.PAGE_RATE_CONTENT = f"{2 * TRAJECTORY_COST}/day"
    record = upload(alice, 1, plaintext=odometry("alice", 0, 0))
    client.force_login(alice.owner.user)
    url = reverse("record-trajectory", args=[record.id])
    assert client.get(url).status_code == 200
    assert client.get(url).status_code == 200
    assert client.get(url).status_code == 429
    assert client.get(reverse("record-detail", args=[record.id])).status_code == 429


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
    down = redis.Redis(port=free_port(), socket_connect_timeout=1)
    monkeypatch.setattr("accounts.decorators.get_redis", lambda: down)
    client.force_login(alice.owner.user)
    for _ in range(3):
        assert client.get(reverse("dashboard")).status_code == 200


def test_anonymous_requests_go_to_sign_in_uncounted(client, settings):
    settings.PAGE_RATE_USER = "1/day"
    for _ in range(3):
        assert client.get(reverse("records")).status_code == 302
