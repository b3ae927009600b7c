"""One lookup of an owner by username or 0x address (accounts.selectors.owner_by_identifier),
used by the grant pages, the grant API and the robot_create command alike."""

import pytest

from accounts.models import Owner
from accounts.selectors import owner_by_identifier
from accounts.services.owners import owner_create
from sharing.errors import OwnerNotFound
from sharing.selectors.grants import owner_resolve
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


@pytest.fixture
def pending_owner(db):
    """An owner whose chain work is never run: the lookup needs only its row."""

    def make(username: str) -> Owner:
        return owner_create(username=username, password=TEST_PASSWORD, sm4_key=sm4.generate_key())

    return make


def test_owners_are_found_by_username_or_by_address_in_any_case(pending_owner):
    pending_owner("bob")
    alice = pending_owner("alice")
    address = alice.eoa_address
    for identifier in (
        "alice",
        "  alice\n",
        address,
        address.lower(),
        "0x" + address[2:].upper(),
        "0X" + address[2:].lower(),
        f" {address} ",
    ):
        assert owner_by_identifier(identifier) == alice, identifier


@pytest.mark.parametrize(
    "identifier",
    ["", "   ", "nobody", "Alice", "0x", "0x" + "00" * 20, "ali\x00ce", "0x\x00", "x" * 300],
)
def test_anything_else_names_nobody(pending_owner, identifier):
    pending_owner("alice")
    assert owner_by_identifier(identifier) is None
    with pytest.raises(OwnerNotFound):
        owner_resolve(identifier)
