"""A grantee whose access ended is told why on the record's page (issue 48): revoked by its
owner, or the grant expired, with a link to Shared with me; anyone else, and a record the grant
never covered, still gets the one "Record not found" (no oracle of what exists)."""

import uuid
from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from sharing.grant_terms import grant_terms_make
from sharing.models import Grant
from sharing.services.grants import grant_create, grant_revoke

pytestmark = pytest.mark.django_db


@pytest.fixture
def shared(make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    alice = make_robot("alice")
    bob = make_owner("bob")
    record = upload(alice, 1, topic="/odom")
    other = upload(alice, 2, topic="/secret")
    terms = grant_terms_make(owner=alice.owner, topics=["/odom"])
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob, terms=terms)
    return alice, bob, record, other


def _page(client, record_id):
    return client.get(reverse("record-detail", args=[record_id]))


def test_a_revoked_grantee_is_told_and_others_are_not(
    client, shared, make_owner, django_capture_on_commit_callbacks
):
    alice, bob, record, other = shared
    client.force_login(bob.user)
    assert _page(client, record.pk).status_code == 200
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=alice.owner, grantee=bob)
    page = _page(client, record.pk)
    assert page.status_code == 403
    html = page.content.decode()
    revoked = Grant.objects.get(grantee=bob).updated_at
    assert (
        f"Access revoked by owner: alice revoked your access on {revoked:%Y-%m-%d %H:%M:%S} UTC"
        in html
    )
    assert f'href="{reverse("shared")}" data-testid="to-shared"' in html
    assert "Record not found" not in html
    # Outside what the grant covered, or no record at all: the same answer as to anyone.
    for record_id in (other.pk, uuid.uuid4()):
        page = _page(client, record_id)
        assert page.status_code == 404
        assert "Record not found" in page.content.decode()
        assert "revoked" not in page.content.decode().split("<main", 1)[1].split("</h1>")[0]
    client.force_login(make_owner("carol").user)
    page = _page(client, record.pk)
    assert page.status_code == 404
    assert "alice revoked" not in page.content.decode()


def test_an_expired_grantee_is_told_when(client, shared):
    _alice, bob, record, _other = shared
    ended = timezone.now().replace(microsecond=0) - timedelta(hours=2)
    Grant.objects.filter(grantee=bob).update(expires_at=ended)
    client.force_login(bob.user)
    page = _page(client, record.pk)
    assert page.status_code == 403
    assert f"Grant expired on {ended:%Y-%m-%d %H:%M:%S} UTC" in page.content.decode()
