"""Enrollment by the admin, registration of key commitments and key rotation."""

from eth_utils import keccak

ZERO32 = b"\0" * 32
ZERO_ADDRESS = "0x0000000000000000000000000000000000000000"


def test_deployer_is_admin_and_constants(authros, admin):
    assert authros.functions.admin().call() == admin
    assert authros.functions.MAX_BATCH().call() == 256
    assert authros.functions.recordCount().call() == 0


def test_admin_enrolls_an_eoa(authros, admin, newcomer, send, emitted):
    eoa = newcomer
    assert authros.functions.isEnrolled(eoa).call() is False

    receipt = send(authros.functions.enroll(eoa), admin)

    assert emitted(receipt, "Enrolled") == [{"eoa": eoa}]
    assert authros.functions.isEnrolled(eoa).call() is True
    assert authros.functions.isRegistered(eoa).call() is False


def test_only_admin_may_enroll(authros, alice, outsider, newcomer, reverts):
    for caller in (alice, outsider, newcomer):
        with reverts("NotAdmin", caller):
            authros.functions.enroll(newcomer).transact({"from": caller})
    assert authros.functions.isEnrolled(newcomer).call() is False


def test_enroll_refuses_zero_address(authros, admin, reverts):
    with reverts("ZeroAddress"):
        authros.functions.enroll(ZERO_ADDRESS).transact({"from": admin})


def test_enroll_refuses_twice(authros, admin, enrolled_only, alice, reverts):
    for eoa in (enrolled_only, alice):
        with reverts("AlreadyEnrolled", eoa):
            authros.functions.enroll(eoa).transact({"from": admin})


def test_enrolled_eoa_registers_its_commitment(authros, enrolled_only, send, emitted):
    commitment = keccak(text="sm3 commitment")

    receipt = send(authros.functions.register(commitment), enrolled_only)

    assert emitted(receipt, "Registered") == [{"eoa": enrolled_only, "commitment": commitment}]
    assert authros.functions.isRegistered(enrolled_only).call() is True
    assert authros.functions.commitmentOf(enrolled_only).call() == commitment


def test_register_refuses_unenrolled(authros, outsider, reverts):
    with reverts("NotEnrolled", outsider):
        authros.functions.register(keccak(text="c")).transact({"from": outsider})


def test_register_refuses_twice(authros, alice, reverts):
    with reverts("AlreadyRegistered", alice):
        authros.functions.register(keccak(text="again")).transact({"from": alice})


def test_register_refuses_empty_commitment(authros, enrolled_only, reverts):
    with reverts("EmptyCommitment"):
        authros.functions.register(ZERO32).transact({"from": enrolled_only})
    assert authros.functions.isRegistered(enrolled_only).call() is False


def test_rotate_key_replaces_the_commitment(authros, alice, send, emitted):
    old = authros.functions.commitmentOf(alice).call()
    new = keccak(text="rotated key commitment")

    receipt = send(authros.functions.rotateKey(new), alice)

    assert emitted(receipt, "KeyRotated") == [
        {"eoa": alice, "oldCommitment": old, "newCommitment": new}
    ]
    assert authros.functions.commitmentOf(alice).call() == new
    assert authros.functions.isRegistered(alice).call() is True


def test_rotate_key_twice_chains_commitments(authros, alice, send, emitted):
    first, second = keccak(text="k1"), keccak(text="k2")
    send(authros.functions.rotateKey(first), alice)

    receipt = send(authros.functions.rotateKey(second), alice)

    assert emitted(receipt, "KeyRotated") == [
        {"eoa": alice, "oldCommitment": first, "newCommitment": second}
    ]
    assert authros.functions.commitmentOf(alice).call() == second


def test_rotate_key_refuses_unregistered(authros, enrolled_only, outsider, reverts):
    for caller in (enrolled_only, outsider):
        with reverts("NotRegistered", caller):
            authros.functions.rotateKey(keccak(text="k")).transact({"from": caller})


def test_rotate_key_refuses_same_commitment(authros, alice, reverts):
    current = authros.functions.commitmentOf(alice).call()
    with reverts("SameCommitment"):
        authros.functions.rotateKey(current).transact({"from": alice})


def test_rotate_key_refuses_empty_commitment(authros, alice, reverts):
    with reverts("EmptyCommitment"):
        authros.functions.rotateKey(ZERO32).transact({"from": alice})


def test_unknown_eoa_views_are_empty(authros, outsider):
    assert authros.functions.isEnrolled(outsider).call() is False
    assert authros.functions.isRegistered(outsider).call() is False
    assert authros.functions.commitmentOf(outsider).call() == ZERO32
