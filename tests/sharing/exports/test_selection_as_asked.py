"""An export holds its selection as of the moment it was asked for (issue 48): a window open
at its end is closed then, so what robots upload while it waits or runs is not in it and its
progress never passes 100% ("5981 of 5858 records checked")."""

import re
from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.exports.create import export_create
from sharing.models import Export
from sharing.selection import RecordSelection
from sharing.services.uploads import record_create_batch

pytestmark = pytest.mark.django_db


def _upload(setup, seqs, moment, django_capture_on_commit_callbacks):
    stamp = moment.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
    envelopes = [setup.seal(seq, time=stamp) for seq in seqs]
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=setup.robot, envelopes=envelopes)


def test_uploads_while_an_export_waits_are_not_in_it(
    alice, client, django_capture_on_commit_callbacks
):
    _upload(
        alice,
        range(1, 4),
        timezone.now() - timedelta(minutes=5),
        django_capture_on_commit_callbacks,
    )
    with django_capture_on_commit_callbacks(execute=False) as queued:
        export = export_create(requester=alice.owner)
    asked = RecordSelection.from_json(export.selection)
    assert asked.until is not None
    assert asked.until.microsecond == 0  # the second asked, rounded up
    assert abs(asked.until - export.created_at) <= timedelta(seconds=1)
    assert export.total == 3

    # The robot goes on uploading before the worker takes the export up.
    _upload(
        alice,
        range(4, 9),
        timezone.now() + timedelta(seconds=2),
        django_capture_on_commit_callbacks,
    )
    for callback in queued:
        callback()
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error
    assert (export.processed, export.total, export.exported) == (3, 3, 3)
    assert export.percent == 100

    client.force_login(alice.owner.user)
    html = client.get(reverse("export-detail", args=[export.pk])).content.decode()
    assert "3 of 3 records checked against the chain, 3 exported." in html
    window = html[html.index('data-testid="export-window"') :]
    window = window[: window.index("</dd>")]
    assert f"up to {asked.until:%Y-%m-%d %H:%M:%S} UTC, when you asked for this export" in window
    assert ".000000" not in window
    assert not re.search(r"\dT\d", window.split(">", 1)[1])


def test_a_window_given_is_kept_and_shown_in_seconds(
    alice, client, django_capture_on_commit_callbacks
):
    now = timezone.now()
    _upload(alice, range(1, 3), now - timedelta(minutes=5), django_capture_on_commit_callbacks)
    since = (now - timedelta(hours=1)).replace(microsecond=250000)
    until = (now + timedelta(hours=1)).replace(microsecond=0)
    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=alice.owner, since=since, until=until)
    assert RecordSelection.from_json(export.selection).until == until
    client.force_login(alice.owner.user)
    html = client.get(reverse("export-detail", args=[export.pk])).content.decode()
    window = html[html.index('data-testid="export-window"') :]
    window = window[: window.index("</dd>")]
    assert f"from {since:%Y-%m-%d %H:%M:%S} UTC, before {until:%Y-%m-%d %H:%M:%S} UTC" in window
    assert "when you asked" not in window
