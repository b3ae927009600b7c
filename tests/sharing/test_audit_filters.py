"""The audit page's filters (issue 12): the kind of transaction, the anchoring of one robot and
a period, as a GET form; a value the form refuses is a 400 that names it, never a 500. The
admin lists the same index, read-only, filterable and searchable."""

import re
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from accounts.models import ChainActivity
from accounts.services.robots import robot_create
from sharing.models import Record
from tests.support.robot_setup import RobotSetup

pytestmark = pytest.mark.django_db

MINUTE_12_00 = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _kinds(html: str) -> list[str]:
    return re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)


def _tx_hashes(html: str) -> set[str]:
    return set(re.findall(r'transaction <span class="hash">(0x[0-9a-f]{64})</span>', html))


@pytest.fixture
def two_robots(client, make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    """alice's robot A uploaded twice and robot B once (three anchoring transactions, the two
    of A seen in the minute 12:00 of 2026-03-01, B's in 12:01), and alice granted bob access."""
    a = make_robot("alice")
    robot_b, token_b = robot_create(owner=a.owner, name="robot-b")
    b = RobotSetup(a.owner, a.key, robot_b, token_b)
    upload(a, 1)
    upload(a, 2)
    upload(b, 1)
    rows = ChainActivity.objects.filter(owner=a.owner, kind="anchored").order_by("id")
    for row, second in zip(rows, (10, 20, 65), strict=True):
        ChainActivity.objects.filter(pk=row.pk).update(at=MINUTE_12_00 + timedelta(seconds=second))
    bob = make_owner("bob")
    client.force_login(a.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    return a, b, bob


def test_kind_filter_lists_only_that_kind(client, two_robots):
    _a, _b, _bob = two_robots
    page = client.get(reverse("audit"), {"kind": "anchored"})
    assert page.status_code == 200
    # Anchoring a minute a line: A's two transactions in 12:00, B's in 12:01.
    assert _kinds(page.content.decode()) == ["upload"] * 2
    granted = client.get(reverse("audit"), {"kind": "granted"}).content.decode()
    assert _kinds(granted) == ["grant-given"]
    assert "Granted access to bob" in granted


def test_robot_filter_lists_the_anchoring_of_that_robot_only(client, two_robots):
    a, b, _bob = two_robots
    of_b = client.get(reverse("audit"), {"robot": str(b.robot.id)}).content.decode()
    assert _kinds(of_b) == ["upload"]
    assert _tx_hashes(of_b) == {Record.objects.get(robot=b.robot).tx_hash}
    of_a = client.get(reverse("audit"), {"robot": str(a.robot.id)}).content.decode()
    assert _tx_hashes(of_a) == set(
        Record.objects.filter(robot=a.robot).values_list("tx_hash", flat=True)
    )
    assert len(_kinds(of_a)) == 1  # both in the minute 12:00
    assert "Anchored 2 records in 12:00 (UTC)" in of_a


def test_period_filter_is_half_open_on_when_the_receipt_was_seen(client, two_robots):
    a, _b, _bob = two_robots
    old = datetime(2024, 1, 10, 12, 0, tzinfo=UTC)
    registered = ChainActivity.objects.get(owner=a.owner, kind="registered")
    ChainActivity.objects.filter(pk=registered.pk).update(at=old)
    in_january = {"since": "2024-01-01", "until": "2024-02-01"}
    page = client.get(reverse("audit"), in_january).content.decode()
    assert _kinds(page) == ["registered"]
    assert _tx_hashes(page) == {registered.tx_hash}
    # `until` is excluded, `since` included.
    assert (
        _kinds(client.get(reverse("audit"), {"until": "2024-01-10T12:00"}).content.decode()) == []
    )
    assert _kinds(client.get(reverse("audit"), {"since": "2024-01-10T12:00"}).content.decode())
    recent = client.get(reverse("audit"), {"since": "2024-02-01"}).content.decode()
    assert registered.tx_hash not in _tx_hashes(recent)
    not_anchoring = ChainActivity.objects.filter(owner=a.owner).exclude(kind="anchored")
    assert len(_kinds(recent)) == not_anchoring.count() - 1 + 2  # two minutes of anchoring
    none = client.get(reverse("audit"), {"kind": "anchored", **in_january}).content.decode()
    assert 'data-testid="audit-none"' in none


def test_filters_keep_the_pages_and_the_filter_in_their_links(client, two_robots, monkeypatch):
    monkeypatch.setattr("sharing.views.audit.AUDIT_ENTRIES_PER_PAGE", 1)
    first = client.get(reverse("audit"), {"kind": "anchored"}).content.decode()
    assert "Page 1 of 2" in first
    assert "?kind=anchored&amp;page=2" in first
    second = client.get(reverse("audit"), {"kind": "anchored", "page": 2}).content.decode()
    assert _kinds(second) == ["upload"]


@pytest.mark.parametrize(
    ("query", "named"),
    [
        ({"kind": "minted"}, "kind"),
        ({"robot": "not-a-uuid"}, "robot"),
        ({"since": "yesterday"}, "since"),
        ({"until": "2024-13-45"}, "until"),
        ({"since": "2024-02-01", "until": "2024-01-01"}, "until"),
    ],
)
def test_a_value_the_form_refuses_is_left_out_and_named(client, two_robots, query, named):
    """The page lists what it lists without that filter, and says which one it left out."""
    everything = _kinds(client.get(reverse("audit")).content.decode())
    page = client.get(reverse("audit"), query)
    html = page.content.decode()
    assert page.status_code == 200
    assert 'class="errorlist' in html
    assert "Left out of the filters" in html
    assert _kinds(html) == everything
    assert f'id="id_{named}_error"' in html
    if query.get("since") == "2024-02-01":
        assert "The start of the time range is after its end." in html


def test_another_owners_robot_is_refused_not_listed(client, two_robots, make_robot, upload):
    carol = make_robot("carol")
    upload(carol, 1)
    page = client.get(reverse("audit"), {"robot": str(carol.robot.id)})
    assert "Left out of the filters" in page.content.decode()
    assert Record.objects.get(robot=carol.robot).tx_hash not in page.content.decode()


def test_a_filtered_page_costs_the_same_queries_however_many_entries(
    client, two_robots, upload, monkeypatch
):
    a, _b, _bob = two_robots
    monkeypatch.setattr("sharing.audit.AUDIT_TRANSACTIONS_PER_MINUTE", 10)

    def queries(query: dict) -> int:
        with CaptureQueriesContext(connection) as seen:
            assert client.get(reverse("audit"), query).status_code == 200
        return len(seen.captured_queries)

    by_robot = {"robot": str(a.robot.id), "since": "2000-01-01"}
    before = queries(by_robot)
    for seq in range(3, 7):
        upload(a, seq)
    assert len(_tx_hashes(client.get(reverse("audit"), by_robot).content.decode())) == 6
    assert queries(by_robot) == before


def test_the_admin_lists_chain_activity_read_only_by_kind_date_and_search(admin_client, two_robots):
    _a, b, _bob = two_robots
    url = reverse("admin:accounts_chainactivity_changelist")
    anchored = admin_client.get(url, {"kind__exact": "anchored"})
    assert anchored.status_code == 200
    assert anchored.context["cl"].result_count == 3
    today = datetime.now(tz=UTC)
    day = timedelta(days=1)
    dated = admin_client.get(
        url, {"at__gte": (today - day).isoformat(), "at__lt": (today + day).isoformat()}
    )
    assert dated.status_code == 200
    moved = ChainActivity.objects.filter(at__lt=today - day).count()  # the fixture's anchoring
    assert dated.context["cl"].result_count == ChainActivity.objects.count() - moved
    tx = Record.objects.get(robot=b.robot).tx_hash
    found = admin_client.get(url, {"q": tx})
    assert [row.tx_hash for row in found.context["cl"].result_list] == [tx]
    by_owner = admin_client.get(url, {"q": "bob"})
    assert (
        by_owner.context["cl"].result_count
        == ChainActivity.objects.filter(owner__user__username="bob").count()
    )
    assert admin_client.get(reverse("admin:accounts_chainactivity_add")).status_code == 403
    row = ChainActivity.objects.filter(kind="anchored").first()
    change = admin_client.post(
        reverse("admin:accounts_chainactivity_change", args=[row.pk]), {"record_count": 99}
    )
    assert change.status_code in (200, 403)
    row.refresh_from_db()
    assert row.record_count != 99
