"""Grants and revocations between registered owners, and the hasAccess identity check."""

import pytest


def test_grant_gives_access(authros, alice, bob, send, emitted):
    assert authros.functions.hasAccess(alice, bob).call() is False

    receipt = send(authros.functions.authorityGrant(bob), alice)

    assert emitted(receipt, "AuthorityGranted") == [{"owner": alice, "grantee": bob}]
    assert authros.functions.hasAccess(alice, bob).call() is True
    assert authros.functions.hasAccess(bob, alice).call() is False  # grants are one-way


def test_grant_refuses_unregistered_caller(authros, enrolled_only, outsider, bob, reverts):
    for caller in (enrolled_only, outsider):
        with reverts("NotRegistered", caller):
            authros.functions.authorityGrant(bob).transact({"from": caller})


def test_grant_refuses_unregistered_grantee(authros, alice, enrolled_only, outsider, reverts):
    for grantee in (enrolled_only, outsider):
        with reverts("GranteeNotRegistered", grantee):
            authros.functions.authorityGrant(grantee).transact({"from": alice})


def test_grant_refuses_self(authros, alice, reverts):
    with reverts("SelfGrant"):
        authros.functions.authorityGrant(alice).transact({"from": alice})


def test_grant_refuses_twice(authros, alice, bob, send, reverts):
    send(authros.functions.authorityGrant(bob), alice)
    with reverts("AlreadyGranted", bob):
        authros.functions.authorityGrant(bob).transact({"from": alice})


def test_revoke_removes_access(authros, alice, bob, send, emitted):
    send(authros.functions.authorityGrant(bob), alice)

    receipt = send(authros.functions.authorityRevoke(bob), alice)

    assert emitted(receipt, "AuthorityRevoked") == [{"owner": alice, "grantee": bob}]
    assert authros.functions.hasAccess(alice, bob).call() is False


def test_revoke_refuses_absent_grant(authros, alice, bob, carol, send, reverts):
    with reverts("NoGrant", bob):
        authros.functions.authorityRevoke(bob).transact({"from": alice})
    # A grant the other way round is not the caller's to revoke.
    send(authros.functions.authorityGrant(alice), bob)
    with reverts("NoGrant", bob):
        authros.functions.authorityRevoke(bob).transact({"from": alice})
    with reverts("NoGrant", carol):
        authros.functions.authorityRevoke(carol).transact({"from": alice})


def test_revoke_refuses_twice(authros, alice, bob, send, reverts):
    send(authros.functions.authorityGrant(bob), alice)
    send(authros.functions.authorityRevoke(bob), alice)
    with reverts("NoGrant", bob):
        authros.functions.authorityRevoke(bob).transact({"from": alice})


def test_revoke_refuses_unregistered_caller(authros, outsider, bob, reverts):
    with reverts("NotRegistered", outsider):
        authros.functions.authorityRevoke(bob).transact({"from": outsider})


def test_grant_again_after_revoke(authros, alice, bob, send, emitted):
    send(authros.functions.authorityGrant(bob), alice)
    send(authros.functions.authorityRevoke(bob), alice)

    receipt = send(authros.functions.authorityGrant(bob), alice)

    assert emitted(receipt, "AuthorityGranted") == [{"owner": alice, "grantee": bob}]
    assert authros.functions.hasAccess(alice, bob).call() is True


def test_grant_survives_key_rotation(authros, alice, bob, send):
    send(authros.functions.authorityGrant(bob), alice)
    send(authros.functions.rotateKey(b"\x01" * 32), alice)
    send(authros.functions.rotateKey(b"\x02" * 32), bob)
    assert authros.functions.hasAccess(alice, bob).call() is True


@pytest.fixture
def granted(authros, alice, bob, carol, send):
    """alice -> bob and bob -> carol are granted; alice -> carol was granted and revoked."""
    send(authros.functions.authorityGrant(bob), alice)
    send(authros.functions.authorityGrant(carol), bob)
    send(authros.functions.authorityGrant(carol), alice)
    send(authros.functions.authorityRevoke(carol), alice)


def test_has_access_matrix(authros, granted, alice, bob, carol, enrolled_only, outsider):
    # (owner, viewer) -> expected; owners always see their own data, nobody else by default.
    expected = {
        (alice, alice): True,
        (alice, bob): True,
        (alice, carol): False,  # revoked
        (bob, alice): False,
        (bob, bob): True,
        (bob, carol): True,
        (carol, alice): False,
        (carol, bob): False,  # grants are not transitive or symmetric
        (carol, carol): True,
        (alice, outsider): False,
        (outsider, alice): False,
        (enrolled_only, enrolled_only): False,  # not registered: no data of its own
        (outsider, outsider): False,
    }
    actual = {pair: authros.functions.hasAccess(*pair).call() for pair in expected}
    assert actual == expected
