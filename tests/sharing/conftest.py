"""Fixtures of the sharing tests: alice with a robot, bob with alice's grant, and the page
tests' upload."""

import pytest

from sharing.services import grant_create
from tests.pages.conftest import upload  # noqa: F401  (the fixture, for tests/sharing/)


@pytest.fixture
def alice(make_robot):
    return make_robot("alice")


@pytest.fixture
def bob(make_owner, alice, django_capture_on_commit_callbacks):
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice.owner, grantee=bob)
    return bob
