"""Filter choices keep to the reader's scope (issue 37.3): the access log's robots and topics
and the shared-records filter's robots are those of records a live grant lets the reader read
now; a revoked or expired grant lists nothing."""

from datetime import timedelta

import pytest
from django.urls import reverse
from django.utils import timezone

from accounts.services.robots import robot_create
from sharing.grant_terms import grant_terms_make
from sharing.models import Grant
from sharing.selectors.access import ACCESS_LOG_OUTGOING, access_log_filter_choices
from sharing.selectors.records import robots_visible_to
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create
from tests.support.robot_setup import seal_for

pytestmark = pytest.mark.django_db


@pytest.fixture
def world(make_robot, make_owner, django_capture_on_commit_callbacks):
    """Alice's robots `shown` (odometry and camera) and `hidden`; Bob may read `shown`'s
    odometry only."""
    alice = make_robot("alice")
    hidden, _ = robot_create(owner=alice.owner, name="hidden-arm")
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        record_create(robot=alice.robot, data=alice.seal(1, topic="/odom"))
        record_create(
            robot=alice.robot,
            data=alice.seal(2, topic="/secret-cam", data_type="sensor_msgs/Image"),
        )
        record_create(robot=hidden, data=seal_for(hidden, alice.key, seq=1, topic="/hidden"))
        terms = grant_terms_make(owner=alice.owner, robots=[alice.robot.pk], topics=["/odom"])
        grant_create(owner=alice.owner, grantee=bob, terms=terms)
    return alice, hidden, bob


def _choices(bob) -> tuple[set, set, set]:
    found = access_log_filter_choices(bob, direction=ACCESS_LOG_OUTGOING)
    robots = {name for _id, name, _owner in found["robots"]}
    return robots, set(found["topics"]), set(found["people"])


def test_choices_keep_to_the_grant_scope(world, client):
    alice, _hidden, bob = world
    assert _choices(bob) == ({alice.robot.name}, {"/odom"}, {"alice"})
    assert [r.name for r in robots_visible_to(bob, shared=True)] == [alice.robot.name]
    client.force_login(bob.user)
    page = client.get(reverse("shared")).content.decode()
    assert alice.robot.name in page
    assert "hidden-arm" not in page
    log = client.get(reverse("access-log"), {"direction": ACCESS_LOG_OUTGOING}).content.decode()
    assert "/secret-cam" not in log
    assert "hidden-arm" not in log


def test_a_revoked_grant_lists_nothing(world, django_capture_on_commit_callbacks):
    alice, _hidden, bob = world
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=alice.owner, grantee=bob)
    assert _choices(bob) == (set(), set(), set())
    assert not robots_visible_to(bob, shared=True).exists()


def test_an_expired_grant_lists_nothing(world):
    _alice, _hidden, bob = world
    Grant.objects.filter(grantee=bob).update(expires_at=timezone.now() - timedelta(seconds=1))
    assert _choices(bob) == (set(), set(), set())
    assert not robots_visible_to(bob, shared=True).exists()
