"""The access log is about others (issue 48): who read the owner's records lists the owner's
own views only when asked for, says how many it left out, and links to them; the CSV agrees."""

import re

import pytest
from django.urls import reverse

from sharing.services.grants import grant_create

pytestmark = pytest.mark.django_db


def _lines(html: str) -> int:
    return len(re.findall(r'data-testid="access-log-row"', html))


def test_own_views_are_left_out_unless_asked(
    client, make_robot, make_owner, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    bob = make_owner("bob")
    record = upload(alice, 1)
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    page = reverse("record-detail", args=[record.pk])
    client.force_login(alice.owner.user)
    for _ in range(3):
        assert client.get(page).status_code == 200
    client.force_login(bob.user)
    assert client.get(page).status_code == 200

    client.force_login(alice.owner.user)
    log = reverse("access-log")
    html = client.get(log).content.decode()
    assert _lines(html) == 1
    assert re.search(r'data-testid="access-log-count">1 access\.', html)
    said = re.search(r'data-testid="own-views-hidden">([^<]*)<a href="([^"]+)"', html)
    assert said is not None
    assert said.group(1) == "3 of your own views not listed: "
    # summed up: the three record pages of the hour are one line
    hours = re.findall(r'data-testid="own-views-hour" data-kind="(\w+)" data-views="(\d+)"', html)
    assert hours == [("view", "3")]
    shown = client.get(log + said.group(2).replace("&amp;", "&")).content.decode()
    assert _lines(shown) == 4
    assert 'data-testid="own-views-hidden"' not in shown
    # Naming oneself as the viewer lists them too; the CSV leaves them out as the page does.
    assert _lines(client.get(log, {"viewer": "alice"}).content.decode()) == 3
    csv = b"".join(client.get(reverse("access-log-csv")).streaming_content).decode()
    assert len(csv.strip().splitlines()) == 2  # the header and bob's line
    csv = b"".join(client.get(reverse("access-log-csv"), {"mine": "on"}).streaming_content)
    assert len(csv.decode().strip().splitlines()) == 5
    # The other side of the log (the owner's reads of records shared with them) is unchanged.
    client.force_login(bob.user)
    outgoing = client.get(log, {"direction": "outgoing"}).content.decode()
    assert _lines(outgoing) == 1
