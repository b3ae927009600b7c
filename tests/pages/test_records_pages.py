"""The record pages as people use them (issue 16): sorting, the robot filter, page numbers,
bad parameters, the dashboard's counts, the wording of the shared page and the record page,
the odometry plot over a chosen range and the image gallery of a range.

The browser side (the row opens the record, cards and no overflow on a phone) is
tests/e2e/test_records_browse.py.
"""

import re
from datetime import UTC, datetime, timedelta
from urllib.parse import quote

import pytest
from django.urls import reverse
from django.utils import timezone

from accounts.services.robots import robot_create
from sharing.models import Record, Verdict
from sharing.selectors.record_pages import RecordCursor
from sharing.services.grants import grant_create
from tests.pages.conftest import fig4, image, odometry
from tests.support.robot_setup import RobotSetup
from tests.support.tampering import tamper

pytestmark = pytest.mark.django_db

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _at(seconds: float) -> str:
    return (NOON + timedelta(seconds=seconds)).isoformat().replace("+00:00", "Z")


def _rows(html: str) -> list[str]:
    return re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="record-row"', html)


@pytest.fixture
def alice(make_robot) -> RobotSetup:
    return make_robot("alice")


@pytest.fixture
def fleet(alice, upload) -> dict[str, Record]:
    """Four records of alice on two robots ("b-cart" and "a-arm"), a minute apart, in the
    three anchoring states; no chain work (anchor=False) except for the anchored one."""
    arm, _token = robot_create(owner=alice.owner, name="a-arm")
    alice.robot.name = "b-cart"
    alice.robot.save(update_fields=["name"])
    other = RobotSetup(alice.owner, alice.key, arm, "")
    made = {
        "odom": upload(alice, 1, time=_at(0), topic="/odom", anchor=True),
        "chat": upload(alice, 2, anchor=False, time=_at(60), topic="/chatter"),
        "scan": upload(other, 1, anchor=False, time=_at(120), topic="/scan"),
        "cam": upload(other, 2, anchor=False, time=_at(180), topic="/cam"),
    }
    Record.objects.filter(pk=made["chat"].pk).update(status=Record.Status.FAILED)
    return made


def _ids(fleet: dict[str, Record], *names: str) -> list[str]:
    return [str(fleet[name].pk) for name in names]


def test_sort_filter_pages_and_bad_parameters(client, fleet, make_robot, upload, monkeypatch):
    owner = fleet["odom"].owner
    client.force_login(owner.user)
    url = reverse("records")

    # Sorting by each column, both ways.
    cases = {
        "": ["cam", "scan", "chat", "odom"],
        "-captured": ["cam", "scan", "chat", "odom"],
        "captured": ["odom", "chat", "scan", "cam"],
        "topic": ["cam", "chat", "odom", "scan"],
        "-topic": ["scan", "odom", "chat", "cam"],
        "robot": ["scan", "cam", "odom", "chat"],  # a-arm first, then by time
        "-robot": ["chat", "odom", "cam", "scan"],
        "status": ["odom", "chat", "scan", "cam"],  # anchored, failed, pending
        "-status": ["cam", "scan", "chat", "odom"],
    }
    for sort, expected in cases.items():
        page = client.get(url, {"sort": sort})
        assert page.status_code == 200, sort
        assert _rows(page.content.decode()) == _ids(fleet, *expected), sort
    # The column headers link to their sort, the current one to its reverse.
    html = client.get(url, {"sort": "topic"}).content.decode()
    # ... in the list as of its newest record when it was opened (the `top` cursor).
    top = quote(str(RecordCursor.of(Record.objects.get(pk=fleet["cam"].pk))))
    assert re.search(rf'href="\?sort=-topic&amp;top={top}"[^>]*aria-sort="ascending"', html)
    assert f'href="?sort=robot&amp;top={top}"' in html

    # The robot filter, alone and with the others.
    arm = fleet["scan"].robot
    assert f'<option value="{arm.pk}">a-arm</option>' in html
    assert _rows(client.get(url, {"robot": str(arm.pk)}).content.decode()) == _ids(
        fleet, "cam", "scan"
    )
    both = {"robot": str(arm.pk), "topic": "/scan", "status": "pending", "sort": "captured"}
    assert _rows(client.get(url, both).content.decode()) == _ids(fleet, "scan")

    # The first column opens the record; every cell is labelled for a phone's cards.
    for record in fleet.values():
        row = html[html.index(f'data-record-id="{record.pk}"') :]
        first_cell = row[: row.index("</td>")]
        # With the list's filters, for the record page's "back to the list" (issue 35).
        assert f'href="{reverse("record-detail", args=[record.pk])}?list=' in first_cell
        assert 'class="row-link"' in first_cell
    assert ">View<" not in html
    assert html.count('data-label="Upload #"') == 4

    # Bad parameters: the page without them, saying what was left out and why; never a 500.
    zed = make_robot("zed")
    upload(zed, 1, anchor=False)
    everything = _rows(client.get(url).content.decode())
    for params in (
        {"sort": "owner__user__password"},
        {"sort": "-captured; DROP TABLE"},
        {"robot": str(zed.robot.pk)},  # someone else's robot
        {"robot": "not-a-robot"},
        {"status": "lost"},
        {"since": "yesterday"},
    ):
        page = client.get(url, params)
        assert page.status_code == 200, params
        html = page.content.decode()
        assert "Select a valid choice" in html or "Enter a valid date/time" in html, params
        assert "Left out of the filters, as they do not hold:" in html
        assert _rows(html) == everything, params
        assert zed.robot.name not in html
    # The filters that hold still apply beside one that does not.
    page = client.get(url, {"robot": str(fleet["scan"].robot.pk), "status": "lost"})
    assert _rows(page.content.decode()) == _ids(fleet, "cam", "scan")
    assert "Status: Select a valid choice" in page.content.decode()
    # A page number that is no page: the first or the last page, as Django's paginator does.
    for page_number in ("abc", "-1", "0", "99999999999999999999"):
        page = client.get(url, {"page": page_number})
        assert page.status_code == 200, page_number
        assert len(_rows(page.content.decode())) == 4

    # Page numbers: first, previous, a window of numbers, next, last; links keep the filters.
    monkeypatch.setattr("sharing.views.records.RECORDS_PER_PAGE", 1)
    html = client.get(url, {"page": 2, "sort": "topic"}).content.decode()
    nav = html[html.index('data-testid="pagination"') :]
    nav = nav[: nav.index("</nav>")]
    assert re.findall(r'data-testid="page-number">(\d+)<', nav) == ["1", "3", "4"]
    assert re.search(r'data-testid="page-current">2<', nav)
    assert f'href="?page=1&amp;sort=topic&amp;top={top}" data-testid="page-first"' in nav
    assert f'href="?page=1&amp;sort=topic&amp;top={top}" rel="prev"' in nav
    assert f'href="?page=3&amp;sort=topic&amp;top={top}" rel="next"' in nav
    assert f'href="?page=4&amp;sort=topic&amp;top={top}" data-testid="page-last"' in nav
    assert _rows(html) == _ids(fleet, "chat")
    first = client.get(url).content.decode()
    assert 'data-testid="page-first"' not in first
    assert 'data-testid="page-last"' in first
    last = client.get(url, {"page": 4, "sort": "topic"}).content.decode()
    assert 'data-testid="page-next"' not in last

    # The dashboard counts pending, failed and tampered records, each linking to them.
    Record.objects.filter(pk=fleet["odom"].pk).update(tampered_at=timezone.now())
    html = client.get(reverse("dashboard")).content.decode()
    assert re.search(r'data-testid="record-count">4<', html)
    assert re.search(r'data-testid="pending-count">2 pending<', html)
    assert re.search(r'data-testid="failed-count" class="bad-count">1 failed<', html)
    assert re.search(r'data-testid="tampered-count" class="bad-count">1 tampered<', html)
    assert 'href="/records/?status=tampered"' in html


# --- wording --------------------------------------------------------------------------------


def test_wording_of_the_shared_page_and_of_the_record_page(
    client, alice, make_owner, upload, django_capture_on_commit_callbacks
):
    bob = make_owner("bob")
    client.force_login(bob.user)
    html = client.get(reverse("shared")).content.decode()
    assert "Nobody shares records with you yet." in html
    assert "Owners sharing with you" not in html
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    html = client.get(reverse("shared")).content.decode()
    assert "Owners sharing with you: <strong>alice</strong>" in html
    assert "Nobody shares" not in html
    assert "alice shares records with you, but no records have been uploaded yet." in html

    # The robot's upload counter and the message's own header seq, each named for what it is.
    plaintext = odometry("alice", 1.0, 2.0).replace(b'"seq":1,', b'"seq":1303,')
    record = upload(alice, 1795485635235521, plaintext=plaintext)
    html = client.get(reverse("shared")).content.decode()
    assert "Nobody shares" not in html
    assert "no records have been uploaded yet" not in html
    assert _rows(html) == [str(record.pk)]
    html = client.get(reverse("record-detail", args=[record.id])).content.decode()
    assert re.search(
        r'<dt>Upload sequence</dt><dd data-testid="upload-seq">1795485635235521 ', html
    )
    assert "not the ROS message's seq" in html
    assert re.search(r'<dt>ROS header seq</dt><dd data-testid="ros-seq">1303 ', html)
    assert "<dt>Sequence</dt>" not in html


# --- the plot over a range ------------------------------------------------------------------


@pytest.fixture
def track(alice, upload) -> list[Record]:
    """Six odometry records of alice, ten seconds apart from NOON, along y = x / 2."""
    return [
        upload(alice, seq, plaintext=odometry("alice", seq, seq / 2), time=_at(10 * seq))
        for seq in range(6)
    ]


def _minute(seconds: float) -> str:
    return (NOON + timedelta(seconds=seconds)).strftime("%Y-%m-%dT%H:%M:%S")


def test_the_plot_of_a_chosen_range(client, track, make_owner):
    client.force_login(track[0].owner.user)
    series = "/api/v1/records/series/"
    query = {
        "robot": str(track[0].robot_id),
        "topic": track[0].topic,
        "fields": "position.x,position.y",
        "since": (NOON + timedelta(seconds=10)).isoformat(),
        "until": (NOON + timedelta(seconds=50)).isoformat(),
    }
    body = client.get(series, query).json()
    assert (body["source_records"], body["verified"], body["refused"]) == (4, 4, 0)
    assert [point[1:] for point in body["points"]] == [[s, s / 2] for s in (1.0, 2.0, 3.0, 4.0)]
    # Only the records in the range were checked (and each was).
    checked = set(Verdict.objects.values_list("record_id", flat=True))
    assert checked == {record.pk for record in track[1:5]}

    # The record page offers a range (five minutes either side), and its plot element asks the
    # series API for the very range its form shows, or for the range chosen.
    page = reverse("record-detail", args=[track[2].id])
    html = client.get(page).content.decode()
    assert 'id="plot-range"' in html
    assert 'name="since" value="2026-03-01 11:55"' in html  # five minutes either side, 24-hour
    assert 'name="until" value="2026-03-01 12:05"' in html
    assert _plot_window(html) == ("2026-03-01T11:55:00+00:00", "2026-03-01T12:05:00+00:00")
    html = client.get(page, {"since": "2026-03-01T12:00", "until": "2026-03-01T12:01"}).content
    assert 'name="since" value="2026-03-01T12:00"' in html.decode()
    assert _plot_window(html.decode()) == (
        "2026-03-01T12:00:00+00:00",
        "2026-03-01T12:01:00+00:00",
    )

    # A bad range is a 400 that says so, and checks nothing.
    Verdict.objects.all().delete()
    for params in (
        {**query, "since": query["until"], "until": query["since"]},
        {key: value for key, value in query.items() if key != "until"},
        {**query, "since": "soon"},
    ):
        answer = client.get(series, params)
        assert answer.status_code == 400, params
        assert answer.json()["detail"], params
    assert not Verdict.objects.exists()

    # Nobody else plots alice's topic: nothing of it is counted or checked.
    client.force_login(make_owner("mallory").user)
    answer = client.get(series, query)
    assert answer.status_code == 200
    assert (answer.json()["source_records"], answer.json()["points"]) == (0, [])
    assert not Verdict.objects.exists()


# --- the gallery ----------------------------------------------------------------------------


@pytest.fixture
def shots(alice, upload) -> list[Record]:
    """Five camera images of alice, a second apart from NOON."""
    return [
        upload(
            alice,
            seq,
            plaintext=image("alice"),
            topic="/cam",
            data_type="sensor_msgs/Image",
            time=_at(seq),
        )
        for seq in range(1, 6)
    ]


def test_the_gallery_of_a_range(client, shots, alice, upload, make_owner, monkeypatch):
    monkeypatch.setattr("sharing.views.record.GALLERY_PER_PAGE", 2)
    tamper(shots[1])
    client.force_login(shots[0].owner.user)
    url = reverse("record-gallery", args=[shots[0].id])
    page = client.get(url)  # five minutes either side of the record by default
    html = page.content.decode()
    assert page.status_code == 200
    assert "5 image records in this range, 2 a page" in html
    items = re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="gallery-item"', html)
    assert items == [str(shots[0].pk), str(shots[1].pk)]
    assert len(re.findall(r'data-testid="gallery-image"', html)) == 1
    assert re.search(r'<img src="data:image/png;base64,iVBORw0KGgo', html)
    assert "TAMPERED: not shown" in html
    assert Verdict.objects.get(record=shots[1]).outcome == "tampered"
    # Only the images on the page were checked.
    assert set(Verdict.objects.values_list("record_id", flat=True)) == {s.pk for s in shots[:2]}
    assert re.search(r'data-testid="page-last">Last<', html)

    third = client.get(url, {"page": 3}).content.decode()
    assert re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="gallery-item"', third) == [
        str(shots[4].pk)
    ]
    narrow = client.get(url, {"since": _minute(2), "until": _minute(4)}).content.decode()
    assert "2 image records in this range" in narrow

    # What the gallery cannot show: a bad range, a record that is no image, someone else's.
    Verdict.objects.all().delete()
    bad = client.get(url, {"since": _minute(4), "until": _minute(1)})
    assert bad.status_code == 400
    assert "after its end" in bad.content.decode()
    text = upload(alice, 9, plaintext=fig4("alice", "std_msgs/String", "/chat", {"data": "x"}))
    assert client.get(reverse("record-gallery", args=[text.id])).status_code == 404
    client.force_login(make_owner("mallory").user)
    assert client.get(url).status_code == 404
    assert not Verdict.objects.exists()


def _plot_window(html: str) -> tuple[str, str]:
    """The range the page's trajectory plot asks the series API for."""
    plot = re.search(r'<div class="series-plot" id="trajectory-plot"[^>]*>', html).group(0)
    since = re.search(r'data-since="([^"]+)"', plot).group(1)
    until = re.search(r'data-until="([^"]+)"', plot).group(1)
    return since, until
