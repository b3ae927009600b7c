"""Whether a record must carry its robot's signature comes from its robot, never from the
record's row (audit turn 4): whoever holds the KEK and the database can seal an envelope under
the owner's key, write its row with a blank `signer` under a paired robot and have the portal
anchor it from the owner's account; the check must refuse it as it refuses a bad signature, and
no page may call it a record of a robot added by hand. Against the session's anvil."""

import pytest

from sharing.models import Record, Verdict
from sharing.services.grants import grant_create
from sharing.verification.check import records_verify
from smcrypto import envelope, sm2
from tests.api.conftest import RECORDS, session_client, token_client
from tests.support.batches import seal_batch
from tests.support.tampering import stored_behind_the_portal

pytestmark = pytest.mark.django_db


def test_an_unsigned_record_written_under_a_paired_robot_is_refused_and_not_called_hand_made(
    make_paired_robot, make_owner, make_owner_token, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=setup.owner, grantee=bob)
    forged = setup.seal(1, signing_key=None)  # unsigned, sealed with the owner's key
    assert envelope.provenance_format(envelope.read_header(forged).header) == "unsigned"
    record = stored_behind_the_portal(setup, forged, django_capture_on_commit_callbacks, signer="")
    assert record.block_number is not None
    for viewer in (setup.owner, bob):
        verdict = records_verify(record_ids=[record.id], viewer_id=viewer.pk)[0].verdict
        assert verdict.outcome == Verdict.Outcome.SIGNATURE_REFUSED
        _token, key = make_owner_token(viewer, scopes=("read",))
        answer = token_client(key).get(f"{RECORDS}{record.id}/content/")
        assert answer.status_code == 409, answer.content
        assert answer.json()["error"] == "integrity_check_failed"
        assert "signature" in answer.json()["detail"]
        page = session_client(viewer).get(f"/records/{record.id}/")
        html = page.content.decode()
        assert page.status_code == 409
        assert 'data-verdict="signature_refused"' in html
        assert "added by hand" not in html
        assert 'data-testid="paired-unsigned"' in html
        assert '"seq": 1' not in html  # nothing of its content


def test_a_row_that_does_not_state_its_anchored_envelope_is_refused(
    make_paired_robot, django_capture_on_commit_callbacks
):
    """A genuine v2 envelope of the robot's, its row written with another topic_seq (what the
    completeness answer counts) or no signer: the row must say what the envelope says."""
    setup = make_paired_robot("alice")
    first, second = seal_batch(setup, [1, 2], topic_seqs=[0, 1])
    signer = setup.robot.key_hash
    relabelled = stored_behind_the_portal(
        setup, first, django_capture_on_commit_callbacks, signer=signer, topic_seq=5
    )
    blanked = stored_behind_the_portal(
        setup, second, django_capture_on_commit_callbacks, signer="", topic_seq=1
    )
    ids = [relabelled.id, blanked.id]
    verdicts = [v.verdict.outcome for v in records_verify(record_ids=ids, viewer_id=setup.owner.pk)]
    assert verdicts == [Verdict.Outcome.SIGNATURE_REFUSED] * 2
    # As the upload stores them, the same envelopes verify.
    Record.objects.filter(pk=relabelled.pk).update(topic_seq=0)
    Record.objects.filter(pk=blanked.pk).update(signer=signer)
    verdicts = [v.verdict.outcome for v in records_verify(record_ids=ids, viewer_id=setup.owner.pk)]
    assert verdicts == [Verdict.Outcome.VERIFIED] * 2


def test_a_robot_added_by_hand_holds_unsigned_records_only(
    make_robot, django_capture_on_commit_callbacks
):
    setup = make_robot("alice")
    unsigned = stored_behind_the_portal(
        setup, setup.seal(1), django_capture_on_commit_callbacks, signer=""
    )
    # It has no key: an envelope naming one is not its, whatever its row says.
    signed = setup.seal(2, signing_key=sm2.generate_keypair())
    said_signed = stored_behind_the_portal(
        setup, signed, django_capture_on_commit_callbacks, signer=""
    )
    ids = [unsigned.id, said_signed.id]
    verdicts = [v.verdict.outcome for v in records_verify(record_ids=ids, viewer_id=setup.owner.pk)]
    assert verdicts == [Verdict.Outcome.VERIFIED, Verdict.Outcome.SIGNATURE_REFUSED]
