"""A record page's way around (issue 35): previous and next of its robot and topic, back to the
list it came from with that list's filters, and a gallery "around this image" that shows it.
"""

import re
from datetime import UTC, datetime, timedelta

import pytest
from django.urls import reverse

from accounts.services.robots import robot_create
from sharing.grant_terms import grant_terms_make
from sharing.services.grants import grant_create
from tests.pages.conftest import image
from tests.support.robot_setup import RobotSetup

pytestmark = pytest.mark.django_db

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)


def _at(seconds: float) -> str:
    return (NOON + timedelta(seconds=seconds)).isoformat().replace("+00:00", "Z")


@pytest.fixture
def alice(make_robot) -> RobotSetup:
    return make_robot("alice")


def _link(html: str, testid: str) -> str | None:
    found = re.search(rf'href="([^"]+)" data-testid="{testid}"', html)
    return found.group(1).replace("&amp;", "&") if found else None


def _tiles(html: str) -> list[str]:
    return re.findall(r'data-record-id="([0-9a-f-]+)" data-testid="gallery-item"', html)


def test_previous_next_and_back_to_the_filtered_list(client, alice, upload):
    # /odom of this robot at 0, 10, 20 s; another topic and another robot in between.
    first = upload(alice, 1, anchor=False, topic="/odom", time=_at(0))
    upload(alice, 2, anchor=False, topic="/scan", time=_at(5))
    middle = upload(alice, 3, anchor=False, topic="/odom", time=_at(10))
    arm, _ = robot_create(owner=alice.owner, name="arm")
    upload(
        RobotSetup(alice.owner, alice.key, arm, ""), 1, anchor=False, topic="/odom", time=_at(15)
    )
    last = upload(alice, 4, anchor=False, topic="/odom", time=_at(20))
    client.force_login(alice.owner.user)

    # The list's row links carry its filters, and the record page links back to them.
    listing = client.get(reverse("records"), {"topic": "/odom", "sort": "captured"})
    row_link = _link(listing.content.decode(), "open-record")
    assert row_link.startswith(reverse("record-detail", args=[first.pk]) + "?list=")

    html = client.get(row_link).content.decode()  # not anchored: a refusal, still navigable
    assert _link(html, "record-previous") is None
    assert 'data-testid="record-no-previous"' in html
    back = _link(html, "record-back")
    assert back.startswith(reverse("records") + "?")
    assert "topic=%2Fodom" in back
    assert "sort=captured" in back
    following = _link(html, "record-next")
    assert following.startswith(reverse("record-detail", args=[middle.pk]) + "?list=")

    html = client.get(following).content.decode()
    assert _link(html, "record-previous").startswith(reverse("record-detail", args=[first.pk]))
    assert _link(html, "record-next").startswith(reverse("record-detail", args=[last.pk]))
    assert _link(html, "record-back") == back  # the same list, two records on

    html = client.get(reverse("record-detail", args=[last.pk])).content.decode()
    assert 'data-testid="record-no-next"' in html
    assert _link(html, "record-back") == reverse("records")  # opened without a list


def test_back_link_stays_on_the_portal(client, alice, upload):
    record = upload(alice, 1, anchor=False, time=_at(0))
    client.force_login(alice.owner.user)
    url = reverse("record-detail", args=[record.pk])
    html = client.get(url, {"list": "https://evil.example/?x=1"}).content.decode()
    back = _link(html, "record-back")
    assert back.startswith(reverse("records") + "?")
    assert "//evil" not in back


def test_a_grantee_steps_only_through_records_it_may_see(
    client, alice, upload, make_owner, on_commit
):
    one = upload(alice, 1, anchor=False, topic="/odom", time=_at(0))
    upload(alice, 2, anchor=False, topic="/odom", time=_at(10))  # outside bob's window
    three = upload(alice, 3, anchor=False, topic="/odom", time=_at(3600))
    bob = make_owner("bob")
    terms = grant_terms_make(
        owner=alice.owner, robots=[], topics=[], since=NOON, until=NOON + timedelta(seconds=5)
    )
    on_commit(
        lambda: grant_create(owner=alice.owner, grantee=bob, made_with="session", terms=terms)
    )
    client.force_login(bob.user)
    html = client.get(reverse("record-detail", args=[one.pk])).content.decode()
    assert _link(html, "record-next") is None  # two is outside the grant's window
    assert str(three.pk) not in (_link(html, "record-next") or "")
    assert _link(html, "record-back") == reverse("shared")


def test_around_this_image_shows_the_image(client, alice, upload):
    images = [
        upload(
            alice,
            seq,
            anchor=False,
            topic="/camera",
            data_type="sensor_msgs/Image",
            plaintext=image("alice"),
            time=_at(-240 + seq),
        )
        for seq in range(1, 14)
    ]
    target = upload(
        alice,
        14,
        anchor=False,
        topic="/camera",
        data_type="sensor_msgs/Image",
        plaintext=image("alice"),
        time=_at(0),
    )
    client.force_login(alice.owner.user)
    html = client.get(reverse("record-gallery", args=[target.pk])).content.decode()
    shown = _tiles(html)
    assert str(target.pk) in shown  # 14 images in the window: it is on the second page
    assert str(images[0].pk) not in shown
    # Asking for a page still gets that page.
    first = client.get(reverse("record-gallery", args=[target.pk]), {"page": "1"})
    shown = re.findall(
        r'data-record-id="([0-9a-f-]+)" data-testid="gallery-item"', first.content.decode()
    )
    assert str(images[0].pk) in shown
