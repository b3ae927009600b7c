"""Fixtures of the sharing tests: alice with a robot, bob with alice's grant, the page tests'
upload, and one run of the reconciliation."""

import pytest

from sharing.services.grants import grant_create
from sharing.services.reconcile import chain_reconcile
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


@pytest.fixture
def reconcile(django_capture_on_commit_callbacks):
    """Run the periodic job once; the tasks it queues run inline."""

    def run() -> dict[str, object]:
        with django_capture_on_commit_callbacks(execute=True):
            return chain_reconcile()

    return run
