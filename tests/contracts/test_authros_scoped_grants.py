"""Scoped and expiring grants: authorityGrantScoped, grantOf, and hasAccess after expiry."""

import pytest
from eth_utils import keccak
from web3.exceptions import ContractLogicError
from web3.logs import DISCARD

from tests.contracts.conftest import decode_revert
from tests.support.anvil_rpc import chain_time_travel

SCOPE = keccak(text="scope-a")  # stand-in for SM3 of a canonical scope encoding
OTHER_SCOPE = keccak(text="scope-b")
ZERO = b"\0" * 32


def _now(w3) -> int:
    return w3.eth.get_block("latest")["timestamp"]


def _time_travel(w3, timestamp: int) -> None:
    """Mine a block at `timestamp` (the node's clock), as later blocks would be."""
    chain_time_travel(w3.provider.endpoint_uri, timestamp)


def test_scoped_grant_sets_terms_and_access(w3, authros, alice, bob, send, emitted):
    expiry = _now(w3) + 3600
    receipt = send(authros.functions.authorityGrantScoped(bob, SCOPE, expiry), alice)

    granted = authros.events.AuthorityGranted().process_receipt(receipt, errors=DISCARD)
    scoped = authros.events.AuthorityScoped().process_receipt(receipt, errors=DISCARD)
    assert [dict(e["args"]) for e in granted] == [{"owner": alice, "grantee": bob}]
    assert [dict(e["args"]) for e in scoped] == [
        {"owner": alice, "grantee": bob, "scope": SCOPE, "expiry": expiry}
    ]
    assert authros.functions.hasAccess(alice, bob).call() is True
    assert authros.functions.grantOf(alice, bob).call() == [True, SCOPE, expiry]


def test_plain_grant_has_all_records_terms(authros, alice, bob, carol, send):
    send(authros.functions.authorityGrant(bob), alice)
    assert authros.functions.grantOf(alice, bob).call() == [True, ZERO, 0]
    assert authros.functions.grantOf(alice, carol).call() == [False, ZERO, 0]


def test_change_of_terms_is_a_new_transaction(w3, authros, alice, bob, send, emitted, reverts):
    send(authros.functions.authorityGrant(bob), alice)
    expiry = _now(w3) + 600

    receipt = send(authros.functions.authorityGrantScoped(bob, OTHER_SCOPE, expiry), alice)

    # A change emits only the new terms: the grant itself existed already.
    assert emitted(receipt, "AuthorityScoped") == [
        {"owner": alice, "grantee": bob, "scope": OTHER_SCOPE, "expiry": expiry}
    ]
    assert authros.functions.grantOf(alice, bob).call() == [True, OTHER_SCOPE, expiry]
    with reverts("SameTerms", bob):
        authros.functions.authorityGrantScoped(bob, OTHER_SCOPE, expiry).transact({"from": alice})
    # The plain grant keeps its meaning: there is a grant already.
    with reverts("AlreadyGranted", bob):
        authros.functions.authorityGrant(bob).transact({"from": alice})


def test_expired_grant_gives_no_access(w3, authros, alice, bob, send):
    expiry = _now(w3) + 100
    send(authros.functions.authorityGrantScoped(bob, ZERO, expiry), alice)

    _time_travel(w3, expiry)

    assert authros.functions.hasAccess(alice, bob).call() is False
    assert authros.functions.grantOf(alice, bob).call() == [False, ZERO, expiry]
    # An expired grant can still be revoked, and then its terms are gone.
    send(authros.functions.authorityRevoke(bob), alice)
    assert authros.functions.grantOf(alice, bob).call() == [False, ZERO, 0]


def test_scoped_grant_refusals(w3, authros, alice, bob, enrolled_only, outsider, reverts):
    scoped = authros.functions.authorityGrantScoped
    with reverts("SelfGrant"):
        scoped(alice, SCOPE, 0).transact({"from": alice})
    with reverts("GranteeNotRegistered", enrolled_only):
        scoped(enrolled_only, SCOPE, 0).transact({"from": alice})
    with reverts("NotRegistered", outsider):
        scoped(bob, SCOPE, 0).transact({"from": outsider})
    # Expiry is checked against the block the transaction is mined in, the next one.
    past = _now(w3) - 1
    with pytest.raises(ContractLogicError) as refused:
        scoped(bob, SCOPE, past).transact({"from": alice})
    name, (expiry, now) = decode_revert(authros.abi, refused.value)
    assert (name, expiry) == ("ExpiryInPast", past)
    assert now > past
    assert authros.functions.grantOf(alice, bob).call() == [False, ZERO, 0]


def test_revoke_clears_terms(authros, alice, bob, send, emitted):
    send(authros.functions.authorityGrantScoped(bob, SCOPE, 0), alice)
    receipt = send(authros.functions.authorityRevoke(bob), alice)
    assert emitted(receipt, "AuthorityRevoked") == [{"owner": alice, "grantee": bob}]
    assert authros.functions.hasAccess(alice, bob).call() is False
    assert authros.functions.grantOf(alice, bob).call() == [False, ZERO, 0]
