"""The grants page's terms: a scoped grant through the form, changing it (prefilled, a new
transaction), form errors that change nothing, and the revocation's confirmation page."""

import re

import pytest
from django.urls import reverse

from sharing.models import Grant

pytestmark = pytest.mark.django_db


def test_change_a_grant_through_the_page(
    client, make_robot, make_owner, upload, django_capture_on_commit_callbacks
):
    alice = make_robot("alice")
    upload(alice, 1, topic="/robot/odom")
    make_owner("bob")
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(reverse("grants"), {"grantee": "bob", "topics": ["/robot/odom"]})
    assert page.status_code == 302
    grant = Grant.objects.get()
    assert (grant.status, grant.scope_topics) == (Grant.Status.ACTIVE, ["/robot/odom"])

    form = client.get(reverse("grants"), {"change": "bob"}).content.decode()
    assert "Change bob's access" in form
    assert re.search(r'value="/robot/odom"[^>]*checked', form)
    assert not re.search(rf'value="{alice.robot.pk}"[^>]*checked', form)
    # Someone given no access, or no one: the empty form, saying so.
    for nobody in ("carol", "0x" + "00" * 20, "\u202e" * 500):
        other = client.get(reverse("grants"), {"change": nobody}).content.decode()
        assert "You give that owner no access to change" in other
        assert "Change bob" not in other

    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(
            reverse("grants"),
            {"grantee": "bob", "change": "True", "robots": [str(alice.robot.pk)]},
        )
    assert page.status_code == 302
    changed = Grant.objects.get()
    assert changed.pk == grant.pk
    assert changed.status == Grant.Status.ACTIVE
    assert (changed.scope_topics, changed.scope_robots) == ([], [str(alice.robot.pk)])
    assert changed.grant_tx != grant.grant_tx  # a new transaction on chain

    # Refusals leave the grant as it is, and say why in words.
    for data, message in [
        ({"expires_at": "2020-01-01T00:00"}, "The expiry must be at least 5 minutes"),
        ({"since": "not a date"}, "Enter a date and time"),
        ({"robots": ["0" * 32]}, "Select a valid choice"),
    ]:
        page = client.post(reverse("grants"), {"grantee": "bob", "change": "True", **data})
        assert page.status_code == 400
        assert message in page.content.decode(), data
    assert Grant.objects.get().scope_robots == [str(alice.robot.pk)]

    # The revocation asks first; a GET of the confirmation changes nothing.
    confirm = client.get(reverse("grant-revoke-confirm"), {"grantee": "bob"})
    assert confirm.status_code == 200
    assert "Revoke bob's access?" in confirm.content.decode()
    assert Grant.objects.get().status == Grant.Status.ACTIVE
    nobody = client.get(reverse("grant-revoke-confirm"), {"grantee": "nobody"}, follow=True)
    assert "There is no access to revoke for that owner." in nobody.content.decode()
