"""A robot key belongs to the owner who registered it (issue 46, finding 3). A robot's public key
is public (every grantee reads it in a proof answer), so another owner may name it in a pairing
request: approving that is refused (409 robot_key_taken, a SecurityEvent, the holder's alert).
And when the node loses the blocks that held an owner's robotKeyAdd while another account's
registration of the same key stays, the chain's first owner (robotKeyOf) is that account: the
reconciliation adds the key again under its owner (robotKeyOfOwner, which nobody else's
registration touches), the records are anchored again after it and verify for the owner, a
grantee and authros-verify, and the dispute is told (an operator alert, a SecurityEvent, the
owner's alert) instead of staying silent.

Against the session's anvil; chain work runs inline, as a worker would run it; "lost blocks"
are the node's snapshot reverted (`blocks_lost`).
"""

import pytest
from django.urls import reverse
from web3 import Web3

from accounts.errors import RobotKeyTaken
from accounts.models import AccountEvent, Robot, RobotPairing
from accounts.services.pairing import robot_pairing_answer, robot_pairing_request
from alerts.models import Alert, AlertKind
from authros_verify.chain import ChainReader
from authros_verify.signature import robot_key_check
from authros_verify.values import Invalid
from chainworker.models import OperatorAlert
from sharing.models import Record, SecurityEvent, Verdict
from sharing.services.grants import grant_create
from sharing.services.reconcile import chain_reconcile
from sharing.verification.check import records_verify
from smcrypto import sm2, sm3, sm4
from tests.api.conftest import RECORDS, token_client
from tests.support.chain_setup import make_registered_owner
from tests.support.robot_setup import RobotSetup

pytestmark = pytest.mark.django_db

DISPUTED = SecurityEvent.Kind.ROBOT_KEY_DISPUTED


def _xy(public_key: str) -> bytes:
    return bytes.fromhex(sm2.public_key_normalize(public_key))[1:]


def _request_naming(public_key: str) -> RobotPairing:
    pairing, _secret = robot_pairing_request(name="copycat", public_key=public_key)
    return pairing


def _outcome(record: Record, viewer) -> str:
    return records_verify(record_ids=[record.id], viewer_id=viewer.pk)[0].verdict.outcome


def test_approving_a_pairing_that_names_another_owners_robot_key_is_refused(
    make_paired_robot, make_owner, on_commit, deployed, client, upload
):
    setup = make_paired_robot("alice")
    mallory = make_owner("mallory")
    # The key as any grantee of alice reads it in a proof answer.
    pairing = _request_naming(sm2.public_key_normalize(setup.signing_key[1]))
    robots = Robot.objects.count()

    client.force_login(mallory.user)
    answer = on_commit(
        lambda: client.post(
            reverse("robot-pair"), {"code": pairing.code, "decision": "approve", "name": ""}
        )
    )

    assert answer.status_code == 409
    assert "already registered to another owner" in answer.content.decode()
    pairing.refresh_from_db()
    assert (pairing.state, pairing.owner, pairing.robot) == (RobotPairing.State.PENDING, None, None)
    assert Robot.objects.count() == robots
    key_hash = bytes.fromhex(setup.robot.key_hash)
    assert deployed.robot_key_of_owner(key_hash, owner=mallory.eoa_address).owner is None
    # Told: the operator and alice (a SecurityEvent on her security page, her alert), and
    # mallory's own security page says what was refused.
    (event,) = SecurityEvent.objects.filter(kind=DISPUTED)
    assert event.owner == setup.owner
    assert event.detail == {
        "where": "pairing",
        "key_hash": setup.robot.key_hash,
        "claimed_by": mallory.eoa_address,
        "robot": str(setup.robot.pk),
        "name": setup.robot.name,
    }
    (alert,) = Alert.objects.filter(kind=AlertKind.ROBOT_KEY_DISPUTED)
    assert alert.owner == setup.owner
    assert "refused" in alert.summary
    assert AccountEvent.objects.filter(
        owner=mallory, kind=AccountEvent.Kind.ROBOT_KEY_TAKEN
    ).exists()
    assert "its key is another owner" in client.get(reverse("security")).content.decode()
    client.force_login(setup.owner.user)
    page = client.get(reverse("security")).content.decode()
    assert "claimed by another owner" in page
    assert mallory.eoa_address in page
    # The service refuses as the page does; alice's robot goes on as before.
    with pytest.raises(RobotKeyTaken, match="remove its key file"):
        robot_pairing_answer(owner=mallory, code=pairing.code, approve=True, actor=mallory.user)
    assert upload(token_client(setup.token), setup.seal(1)).status_code == 201
    assert _outcome(Record.objects.get(), setup.owner) == Verdict.Outcome.VERIFIED


def test_approving_a_pairing_whose_key_another_account_registered_first_on_chain_is_refused(
    make_owner, deployed, operator
):
    """The key's first owner on chain is an account outside this portal: refused as well (the
    SecurityEvent is the approver's: no robot of this portal has the key)."""
    alice = make_owner("alice")
    outsider = make_registered_owner(deployed, operator)
    _private, public_key = sm2.generate_keypair()
    xy = _xy(public_key)
    deployed.robot_key_add(outsider, sm3.sm3_digest(xy), xy)
    pairing = _request_naming(public_key)

    with pytest.raises(RobotKeyTaken):
        robot_pairing_answer(owner=alice, code=pairing.code, approve=True, actor=alice.user)

    assert not Robot.objects.filter(owner=alice).exists()
    (event,) = SecurityEvent.objects.filter(kind=DISPUTED)
    assert (event.owner, event.detail["claimed_by"]) == (alice, outsider.address)
    assert not Alert.objects.filter(kind=AlertKind.ROBOT_KEY_DISPUTED).exists()


def test_after_lost_blocks_another_accounts_registration_of_the_key_takes_no_record_over(
    make_owner, pair_robot, upload, owner_api, blocks_lost, on_commit, deployed, operator
):
    key = sm4.generate_key()
    alice, bob = make_owner("alice", key=key), make_owner("bob")
    mallory = make_registered_owner(deployed, operator)  # an account outside the portal
    on_commit(lambda: grant_create(owner=alice, grantee=bob))
    with blocks_lost():
        paired = pair_robot(alice)
        setup = RobotSetup(alice, key, paired.robot, paired.token, paired.signing_key)
        assert upload(token_client(setup.token), setup.seal(1)).status_code == 201
        record = Record.objects.get()
        assert _outcome(record, bob) == Verdict.Outcome.VERIFIED
    key_hash = bytes.fromhex(setup.robot.key_hash)
    # The node came back without alice's robotKeyAdd; mallory's registration of her robot's
    # key (read in any proof answer) is on it: the chain's first owner of the key is mallory.
    deployed.robot_key_add(mallory, key_hash, _xy(setup.signing_key[1]))
    assert deployed.robot_key_of(key_hash).owner == mallory.address
    assert deployed.robot_key_of_owner(key_hash, owner=alice.eoa_address).owner is None
    # Until the reconciliation, the record waits as the chain has it: not anchored (yet).
    assert _outcome(record, bob) == Verdict.Outcome.NOT_ANCHORED_YET

    counts = on_commit(chain_reconcile)

    assert (counts["robot_keys_lost"], counts["robot_keys_disputed"]) == (1, 1)
    # The operator, alice's security page and alice's alerts say it, once.
    (operator_alert,) = OperatorAlert.objects.filter(kind="robot-key-disputed")
    assert operator_alert.subject == f"robot {setup.robot.pk}"
    assert operator_alert.resolved_at is None
    assert operator_alert.detail["first_owner_on_chain"] == mallory.address
    (event,) = SecurityEvent.objects.filter(kind=DISPUTED)
    assert (event.owner, event.detail["where"]) == (alice, "chain")
    assert event.detail["claimed_by"] == mallory.address
    (alert,) = Alert.objects.filter(kind=AlertKind.ROBOT_KEY_DISPUTED)
    assert alert.owner == alice
    assert mallory.address in alert.summary
    # The key is alice's again, under her own entry, and her record was anchored after it.
    robot = Robot.objects.get(pk=setup.robot.pk)
    on_chain = deployed.robot_key_of_owner(key_hash, owner=alice.eoa_address)
    assert on_chain.added_block == robot.key_added_block
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    assert on_chain.live_at(record.block_number)
    assert deployed.robot_key_of(key_hash).owner == mallory.address  # for old readers, mallory
    # Owner and grantee verify it; the grantee's proof names alice as the key's owner.
    for viewer in (alice, bob):
        assert _outcome(record, viewer) == Verdict.Outcome.VERIFIED
    proof = owner_api(bob).get(f"{RECORDS}{record.id}/proof/").json()
    assert proof["signature"]["key_owner"].lower() == alice.eoa_address.lower()
    assert proof["signature"]["key_added_block"] == on_chain.added_block
    # authros-verify holds the key to the record's owner: alice's registration counts, and
    # mallory's, whoever's record names the key, counts for nobody else.
    reader = ChainReader(Web3(Web3.HTTPProvider(deployed.url)))
    check = {"contract": deployed.address, "signer": robot.key_hash, "block": record.block_number}
    robot_key_check(reader, owner=proof["owner"], **check)
    with pytest.raises(Invalid, match="never registered on chain by its owner"):
        robot_key_check(reader, owner=bob.eoa_address, **check)
    # A second run finds it again, and tells nobody twice.
    again = on_commit(chain_reconcile)
    assert (again["robot_keys_lost"], again["robot_keys_disputed"]) == (0, 1)
    assert SecurityEvent.objects.filter(kind=DISPUTED).count() == 1
    assert Alert.objects.filter(kind=AlertKind.ROBOT_KEY_DISPUTED).count() == 1
    assert OperatorAlert.objects.filter(kind="robot-key-disputed").count() == 1
