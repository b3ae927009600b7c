"""Fixtures of the sharing tests: alice with a robot, bob with alice's grant, the page tests'
upload, one run of the reconciliation, and the SM2 verifications a test runs, counted."""

import pytest

from sharing.services.grants import grant_create
from sharing.services.reconcile import chain_reconcile
from smcrypto import sm2
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


@pytest.fixture
def verifications(monkeypatch):
    """The SM2 verifications run, counted where every check of many runs them
    (sm2.verify_many): the number of claims of each call, in order."""
    counted = []
    real = sm2.verify_many

    def counting(claims):
        counted.append(len(claims))
        return real(claims)

    monkeypatch.setattr(sm2, "verify_many", counting)
    return counted
