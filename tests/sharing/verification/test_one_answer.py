"""One answer for "you may not see this record" (issue 37.7): the content endpoint answers a
record that exists exactly as one that does not (404 `not_found`, the same words), a deleted
record of someone else's is not told apart either, and an owner without a grant leaves one
refused-view row per hour in a row in the other owner's access log, not one per view."""

import uuid
from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.models import Access, Record, Verdict
from sharing.services.deletion import record_delete
from sharing.services.uploads import record_create
from sharing.verification.access import REFUSED_VIEWS_COALESCED
from sharing.verification.check import records_verify
from sharing.verification.opening import records_open
from tests.api.conftest import RECORDS, token_client

pytestmark = pytest.mark.django_db


@pytest.fixture
def anchored(make_robot, django_capture_on_commit_callbacks):
    setup = make_robot("alice")
    with django_capture_on_commit_callbacks(execute=True):
        records = [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in (1, 2)]
    for record in records:
        record.refresh_from_db()
        assert record.status == Record.Status.ANCHORED
    return setup, records


def test_content_answers_alike_whether_the_record_exists_or_not(
    anchored, make_owner, make_owner_token
):
    _setup, (record, _other) = anchored
    mallory = make_owner("mallory")
    api = token_client(make_owner_token(mallory, scopes=("read",))[1])
    for suffix in ("content/", "proof/", ""):
        there = api.get(f"{RECORDS}{record.pk}/{suffix}")
        missing = api.get(f"{RECORDS}{uuid.uuid4()}/{suffix}")
        assert (there.status_code, there.json()) == (missing.status_code, missing.json())
        assert there.status_code == 404
        assert there.json()["error"] == "not_found"
    # The refused content view is still in the access log (the owner's and the viewer's).
    assert Verdict.objects.filter(
        record=record, access__viewer=mallory, outcome="no_access"
    ).exists()


def test_a_deleted_record_of_someone_else_is_not_told_apart(
    anchored, make_owner, make_owner_token, client
):
    setup, (record, _other) = anchored
    record_delete(owner=setup.owner, record_id=record.pk, actor=setup.owner.user)
    mallory = make_owner("mallory")
    api = token_client(make_owner_token(mallory, scopes=("read",))[1])
    there = api.get(f"{RECORDS}{record.pk}/content/")
    missing = api.get(f"{RECORDS}{uuid.uuid4()}/content/")
    assert (there.status_code, there.json()) == (missing.status_code, missing.json())
    client.force_login(mallory.user)
    assert client.get(reverse("record-detail", args=[record.pk])).status_code == 404
    # Its owner still hears that it is deleted.
    own = token_client(make_owner_token(setup.owner, scopes=("read",))[1])
    assert own.get(f"{RECORDS}{record.pk}/content/").status_code == 410


def test_refused_views_in_a_row_leave_one_row_an_hour(anchored, make_owner):
    _setup, records = anchored
    mallory = make_owner("mallory")
    for _ in range(5):
        for record in records:
            (checked,) = records_verify(record_ids=[record.pk], viewer_id=mallory.pk)
            assert checked.verdict.outcome == "no_access"
    refused = Verdict.objects.filter(access__viewer=mallory)
    assert refused.count() == 1
    # An hour later, the next refused view is a row of its own.
    refused.update(created_at=timezone.now() - REFUSED_VIEWS_COALESCED - timedelta(seconds=1))
    records_verify(record_ids=[records[0].pk], viewer_id=mallory.pk)
    assert refused.count() == 2


def test_refused_views_through_the_api_and_pages_leave_one_row_an_hour(
    anchored, make_owner, make_owner_token, client
):
    """The web's reads (the content answer, a record's page) are coalesced as the worker's
    check is: an owner without a grant cannot fill another owner's access log by asking."""
    setup, records = anchored
    mallory = make_owner("mallory")
    api = token_client(make_owner_token(mallory, scopes=("read",))[1])
    client.force_login(mallory.user)
    for _ in range(3):
        for record in records:
            assert api.get(f"{RECORDS}{record.pk}/content/").status_code == 404
            assert client.get(reverse("record-detail", args=[record.pk])).status_code == 404
    assert Verdict.objects.filter(access__viewer=mallory).count() == 1
    assert Access.objects.filter(viewer=mallory).count() == 1
    # The owner's own views are each written.
    own = token_client(make_owner_token(setup.owner, scopes=("read",))[1])
    for _ in range(2):
        assert own.get(f"{RECORDS}{records[0].pk}/content/").status_code == 200
    assert Access.objects.filter(viewer=setup.owner, kind=Access.Kind.VIEW).count() == 2


def test_a_refused_read_of_several_records_is_coalesced_as_a_view_of_one(anchored, make_owner):
    """One path for N records: a read refused whole is coalesced whatever it holds, and a
    read of the web (its line open already) leaves no line of its own when coalesced."""
    setup, records = anchored
    mallory = make_owner("mallory")
    ids = [record.pk for record in records]
    first = records_verify(record_ids=ids, viewer_id=mallory.pk)
    assert [checked.verdict.outcome for checked in first] == ["no_access", "no_access"]
    again = records_verify(record_ids=ids, viewer_id=mallory.pk)
    assert {checked.verdict.pk for checked in again} == {first[-1].verdict.pk}
    assert Verdict.objects.filter(access__viewer=mallory).count() == 2
    assert Access.objects.filter(viewer=mallory).count() == 1
    # A web read of both, coalesced too: its line is gone with it.
    records_open(records=records, viewer=mallory, kind=Access.Kind.PAGE, credential="session")
    assert Access.objects.filter(viewer=mallory).count() == 1
    # The owner's own read of the same records is written each time.
    records_verify(record_ids=ids, viewer_id=setup.owner.pk)
    records_verify(record_ids=ids, viewer_id=setup.owner.pk)
    assert Access.objects.filter(viewer=setup.owner).count() == 2
