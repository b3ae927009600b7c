"""`/api/v1/grants/` with terms: optional scope fields and expiry, their refusals (400, and
nothing changes), and changing a grant's terms (PATCH)."""

import json
from datetime import timedelta

import pytest
from django.utils import timezone

from accounts.services.robots import robot_create
from sharing.models import Grant
from tests.api.conftest import GRANTS

pytestmark = pytest.mark.django_db

ZERO = "0" * 64


@pytest.fixture
def alice(make_robot):
    return make_robot("alice")


@pytest.fixture
def bob(make_robot):
    return make_robot("bob")


def _soon(**delta) -> str:
    return (timezone.now() + timedelta(**delta)).isoformat()


def test_terms_are_optional_and_shown(alice, bob, owner_api, django_capture_on_commit_callbacks):
    api = owner_api(alice.owner)
    with django_capture_on_commit_callbacks(execute=True):
        plain = api.post(GRANTS, {"grantee": "bob"}, format="json")
    assert plain.status_code == 201, plain.content
    body = plain.json()
    assert body["scope"] == {
        "robots": [],
        "topics": [],
        "since": None,
        "until": None,
        "commitment": ZERO,
    }
    assert (body["expires_at"], body["expired"]) == (None, False)

    expires = _soon(days=2)
    with django_capture_on_commit_callbacks(execute=True):
        changed = api.patch(
            f"{GRANTS}bob/",
            {
                "robots": [str(alice.robot.pk)],
                "topics": ["/robot/odom"],
                "since": "2026-01-01T00:00:00Z",
                "expires_at": expires,
            },
            format="json",
        )
    assert changed.status_code == 200, changed.content
    assert changed.json()["status"] == "pending"
    listed = api.get(GRANTS).json()["given"][0]
    assert listed["status"] == "active"
    assert listed["scope"]["robots"] == [str(alice.robot.pk)]
    assert listed["scope"]["topics"] == ["/robot/odom"]
    assert listed["scope"]["since"] == "2026-01-01T00:00:00Z"
    assert listed["scope"]["commitment"] not in (ZERO, "")
    assert listed["expires_at"] is not None
    assert listed["grant_tx"] != plain.json()["grant_tx"]
    # The grantee sees the same terms.
    assert owner_api(bob.owner).get(GRANTS).json()["received"][0]["scope"] == listed["scope"]


def test_bad_terms_are_400_and_change_nothing(alice, bob, owner_api):
    carol_robot, _ = robot_create(owner=bob.owner, name="not-alices")
    api = owner_api(alice.owner)
    bad = [
        ({"robots": "all"}, "invalid_request"),
        ({"robots": ["not-a-uuid"]}, "invalid_request"),
        ({"robots": [str(carol_robot.pk)]}, "invalid_grant_terms"),
        ({"topics": [""]}, "invalid_request"),
        ({"topics": ["a" * 256]}, "invalid_request"),
        ({"topics": [5]}, "invalid_request"),
        ({"topics": ["\ud800"]}, "invalid_request"),
        ({"topics": ["x"] * 101}, "invalid_request"),
        ({"since": "yesterday"}, "invalid_request"),
        ({"since": "2026-01-02T00:00:00Z", "until": "2026-01-01T00:00:00Z"}, "invalid_grant_terms"),
        ({"since": "1969-12-31T00:00:00Z"}, "invalid_grant_terms"),
        ({"expires_at": _soon(minutes=-1)}, "invalid_grant_terms"),
        ({"expires_at": _soon(minutes=1)}, "invalid_grant_terms"),
        ({"expires_at": 12}, "invalid_request"),
    ]
    for terms, code in bad:
        # json.dumps escapes a lone surrogate ("\\ud800"), as a hostile client may send it.
        body = json.dumps({"grantee": "bob", **terms})
        answer = api.post(GRANTS, body, content_type="application/json")
        assert answer.status_code == 400, (terms, answer.content)
        assert answer.json()["error"] == code, (terms, answer.json())
        assert answer.json()["detail"]
    assert not Grant.objects.exists()
    # A change of a grant that does not exist is refused too.
    answer = api.patch(f"{GRANTS}bob/", {"topics": ["/robot/odom"]}, format="json")
    assert (answer.status_code, answer.json()["error"]) == (404, "no_grant")
