"""Robots sign what they capture (DESIGN.md "Provenance"): a paired robot's uploads must carry
its own key's signature over their content; a record is genuine at a view only when its anchored
envelope names that key, the key is its owner's on chain at the record's anchoring, and the
signature holds over the content. Against the session's anvil, through the REST API."""

import base64
import json
from datetime import UTC, datetime

import pytest

from accounts.models import ChainState
from accounts.selectors import owner_eoa_account
from sharing.errors import IntegrityCheckFailed
from sharing.models import Record, SecurityEvent, Verdict
from sharing.services import uploads as sharing_uploads
from sharing.services.grants import grant_create
from sharing.services.uploads import record_create
from sharing.verification.check import records_verify
from sharing.verification.opening import record_open
from smcrypto import envelope, provenance, sm2
from tests.api.conftest import RECORDS, Snapshot, token_client

pytestmark = pytest.mark.django_db


def _header(setup, seq: int) -> dict:
    return {
        "owner": setup.owner.username,
        "robot": str(setup.robot.id),
        "topic": "/robot/odom",
        "type": "nav_msgs/Odometry",
        "seq": seq,
        "time": datetime.now(tz=UTC).isoformat().replace("+00:00", "Z"),
    }


def _body(seq: int) -> bytes:
    return json.dumps({"K": {"seq": seq}}).encode()


def _signed_over_other_content(setup, seq: int) -> bytes:
    header = provenance.sign_header(*setup.signing_key, _header(setup, seq), b"other content")
    return envelope.seal(setup.key, header, _body(seq))


def _signed_by_another_key_naming_the_robots(setup, seq: int) -> bytes:
    other = sm2.generate_keypair()
    header = provenance.sign_header(*other, _header(setup, seq), _body(seq))
    header["signer"] = setup.robot.key_hash
    return envelope.seal(setup.key, header, _body(seq))


def _outcome(record: Record, viewer) -> str:
    return records_verify(record_ids=[record.id], viewer_id=viewer.pk)[0].verdict.outcome


def test_a_paired_robots_key_is_its_owners_on_chain(make_paired_robot, deployed):
    setup = make_paired_robot("alice")
    robot = setup.robot
    assert robot.key_hash == provenance.key_hash(setup.signing_key[1])
    assert robot.key_chain_state == ChainState.CONFIRMED
    on_chain = deployed.robot_key_of(bytes.fromhex(robot.key_hash))
    assert on_chain.owner.lower() == setup.owner.eoa_address.lower()
    assert on_chain.revoked_block is None


def test_signed_records_verify_for_owner_and_grantee_with_a_proof_anyone_can_check(
    make_paired_robot, make_owner, upload, owner_api, django_capture_on_commit_callbacks, client
):
    setup = make_paired_robot("alice")
    response = upload(token_client(setup.token), setup.seal(1))
    assert response.status_code == 201, response.content
    record = Record.objects.get()
    assert record.signer == setup.robot.key_hash
    assert record.status == Record.Status.ANCHORED
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=setup.owner, grantee=bob)
    for viewer in (setup.owner, bob):
        assert _outcome(record, viewer) == Verdict.Outcome.VERIFIED
    opened = record_open(record_id=record.id, viewer=bob)
    assert opened.header["signer"] == setup.robot.key_hash  # the re-sealed copy keeps it
    client.force_login(bob.user)
    page = client.get(f"/records/{record.id}/").content.decode()
    assert 'data-testid="verified-signature">robot key' in page
    assert setup.robot.key_hash in page

    proof = owner_api(bob).get(f"{RECORDS}{record.id}/proof/").json()
    signature = proof["signature"]
    assert signature["signer"] == record.signer
    assert signature["key_owner"].lower() == setup.owner.eoa_address.lower()
    assert signature["key_added_block"] <= proof["anchor"]["block"]
    assert signature["key_revoked_block"] is None
    # What a grantee checks without the portal: the anchored envelope, opened with the key
    # the grantee was given, signed over that very content by the key the chain names.
    stored = base64.b64decode(proof["envelope"])
    header, plaintext = envelope.open(setup.key, stored)
    assert "0x" + envelope.digest(stored).hex() == proof["digest"]
    assert provenance.key_hash(signature["public_key"]) == signature["signer"]
    assert provenance.verify_header(signature["public_key"], header, plaintext)
    assert signature["sig"] == header["sig"]


@pytest.mark.parametrize(
    ("make_envelope", "kind"),
    [
        (lambda setup, seq: setup.seal(seq, signing_key=None), "unsigned_upload"),
        (
            lambda setup, seq: setup.seal(seq, signing_key=sm2.generate_keypair()),
            "foreign_signer",
        ),
        (_signed_over_other_content, "bad_signature"),
        (_signed_by_another_key_naming_the_robots, "bad_signature"),
    ],
    ids=["unsigned", "another-key", "other-content", "another-key-naming-the-robots"],
)
def test_a_paired_robots_upload_not_signed_by_its_key_is_refused_and_nothing_stored(
    make_paired_robot, upload, make_envelope, kind
):
    setup = make_paired_robot("alice")
    before = Snapshot()
    response = upload(token_client(setup.token), make_envelope(setup, 1))
    assert response.status_code == 403
    assert response.json()["error"] == "signature_refused"
    assert before.unchanged()
    event = SecurityEvent.objects.get()
    assert (event.kind, event.owner_id, event.detail["seq"]) == (kind, setup.owner.pk, 1)
    # The robot's own signed envelope with the same seq is taken afterwards.
    assert upload(token_client(setup.token), setup.seal(1)).status_code == 201


def test_a_batch_with_one_unsigned_envelope_stores_none(make_paired_robot, upload):
    setup = make_paired_robot("alice")
    before = Snapshot()
    envelopes = [setup.seal(1), setup.seal(2, signing_key=None), setup.seal(3)]
    response = upload(token_client(setup.token), *envelopes)
    assert response.status_code == 403
    assert before.unchanged()


def test_a_robot_added_by_hand_uploads_unsigned_records_never_shown_as_signed(
    make_robot, upload, owner_api
):
    setup = make_robot("alice")
    assert upload(token_client(setup.token), setup.seal(1)).status_code == 201
    record = Record.objects.get()
    assert record.signer == ""
    assert _outcome(record, setup.owner) == Verdict.Outcome.VERIFIED
    api = owner_api(setup.owner)
    assert api.get(f"{RECORDS}{record.id}/").json()["signer"] is None
    assert api.get(f"{RECORDS}{record.id}/proof/").json()["signature"] is None
    # It has no key: an envelope of its naming one is refused.
    signed = setup.seal(2, signing_key=sm2.generate_keypair())
    response = upload(token_client(setup.token), signed)
    assert (response.status_code, response.json()["error"]) == (403, "signature_refused")
    assert SecurityEvent.objects.get().kind == SecurityEvent.Kind.FOREIGN_SIGNER


@pytest.mark.parametrize(
    "forge",
    [_signed_over_other_content, _signed_by_another_key_naming_the_robots],
    ids=["other-content", "another-key"],
)
def test_a_record_forged_with_the_owners_key_and_account_fails_every_check(
    make_paired_robot, monkeypatch, django_capture_on_commit_callbacks, forge, client
):
    """Whoever holds the KEK and the database can seal under the owner's key and anchor from
    the owner's account, skipping the upload's check: without the robot's private key the
    record is never genuine."""
    setup = make_paired_robot("alice")
    monkeypatch.setattr(sharing_uploads, "_signatures_hold", lambda robot, checked: None)
    with django_capture_on_commit_callbacks(execute=True):
        record = record_create(robot=setup.robot, data=forge(setup, 1))
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED  # anchored from the owner's EOA
    assert _outcome(record, setup.owner) == Verdict.Outcome.SIGNATURE_REFUSED
    with pytest.raises(IntegrityCheckFailed, match="signature"):
        record_open(record_id=record.id, viewer=setup.owner)
    client.force_login(setup.owner.user)
    page = client.get(f"/records/{record.id}/")
    html = page.content.decode()
    assert page.status_code == 409
    assert 'data-verdict="signature_refused"' in html
    assert "Signature not valid" in html
    assert '"seq": 1' not in html  # nothing of its content


def test_records_anchored_after_the_key_was_revoked_on_chain_are_not_genuine(
    make_paired_robot, upload, deployed
):
    setup = make_paired_robot("alice")
    assert upload(token_client(setup.token), setup.seal(1)).status_code == 201
    before = Record.objects.get()
    deployed.robot_key_revoke(owner_eoa_account(setup.owner), bytes.fromhex(setup.robot.key_hash))
    assert upload(token_client(setup.token), setup.seal(2)).status_code == 201
    after = Record.objects.get(seq=2)
    assert after.status == Record.Status.ANCHORED
    assert _outcome(before, setup.owner) == Verdict.Outcome.VERIFIED  # signed while live
    assert _outcome(after, setup.owner) == Verdict.Outcome.SIGNATURE_REFUSED


def test_a_robot_whose_key_could_not_be_registered_is_refused(make_paired_robot, upload):
    """The robot's key could never be added under its owner (the owner had revoked it before):
    its records could never be genuine, so its uploads are refused until it is paired again."""
    setup = make_paired_robot("alice")
    type(setup.robot).objects.filter(pk=setup.robot.pk).update(key_chain_state=ChainState.FAILED)
    before = Snapshot()
    response = upload(token_client(setup.token), setup.seal(1))
    assert (response.status_code, response.json()["error"]) == (403, "signature_refused")
    assert "pair the robot again" in response.json()["detail"]
    assert before.unchanged()


def test_a_run_over_many_records_of_one_robot_asks_the_chain_for_its_key_once(
    make_paired_robot, upload, deployed, monkeypatch
):
    setup = make_paired_robot("alice")
    envelopes = [setup.seal(seq) for seq in range(1, 4)]
    assert upload(token_client(setup.token), *envelopes).status_code == 201
    asked = []
    real = deployed.robot_key_of_owner
    monkeypatch.setattr(
        deployed,
        "robot_key_of_owner",
        lambda key, *, owner: asked.append(key) or real(key, owner=owner),
    )
    ids = list(Record.objects.values_list("pk", flat=True))
    verifications = records_verify(record_ids=ids, viewer_id=setup.owner.pk)
    assert [v.verdict.outcome for v in verifications] == [Verdict.Outcome.VERIFIED] * 3
    assert asked == [bytes.fromhex(setup.robot.key_hash)]


def test_a_check_of_many_records_refuses_exactly_the_forged_ones_among_them(
    make_paired_robot, monkeypatch, django_capture_on_commit_callbacks
):
    """The signatures of one check are verified side by side on every core: each verdict is
    still its own record's, the forged ones refused wherever they stand in the batch."""
    setup = make_paired_robot("alice")
    monkeypatch.setattr(sharing_uploads, "_signatures_hold", lambda robot, checked: None)
    forged = {1, 9, 16, 23}
    envelopes = [
        _signed_over_other_content(setup, seq) if seq in forged else setup.seal(seq)
        for seq in range(24)
    ]
    with django_capture_on_commit_callbacks(execute=True):
        sharing_uploads.record_create_batch(robot=setup.robot, envelopes=envelopes)
    records = list(Record.objects.order_by("seq"))
    assert {record.status for record in records} == {Record.Status.ANCHORED}
    checked = records_verify(record_ids=[r.id for r in records], viewer_id=setup.owner.pk)
    assert [(c.verdict.record_id, c.verdict.outcome) for c in checked] == [
        (
            record.id,
            Verdict.Outcome.SIGNATURE_REFUSED if record.seq in forged else Verdict.Outcome.VERIFIED,
        )
        for record in records
    ]
    handed_on = [c.envelope is not None for c in checked]
    assert handed_on == [record.seq not in forged for record in records]
