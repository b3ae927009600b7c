"""Records mode (ANCHOR_MODE=records, the paper's per-record anchoring): another registered
account that anchors an owner's record id first no longer fails that record (issue 38). Ids
are bound to their owner on chain (dataQueryOf(owner, id)), as roots are keyed by sender."""

import dataclasses

import pytest

from accounts.selectors import owner_eoa_account
from chainworker.services import chain_client
from sharing.models import Record, SecurityEvent, Verdict
from sharing.services.anchoring import anchor_item
from sharing.services.uploads import record_create
from sharing.verification.check import records_verify
from smcrypto import sm3

pytestmark = pytest.mark.django_db


def test_a_squatted_record_id_does_not_fail_its_owners_record(
    records_mode, make_robot, make_owner, django_capture_on_commit_callbacks
):
    alice, mallory = make_robot("alice"), make_owner("mallory")
    with django_capture_on_commit_callbacks(execute=False) as anchoring:
        record = record_create(robot=alice.robot, data=alice.seal(1))
    # Mallory reads the id (say, from a grant or a log) and anchors it first, with her digest.
    squat = dataclasses.replace(anchor_item(record), digest=sm3.sm3_digest(b"squatted"))
    client = chain_client()
    client.data_upload(owner_eoa_account(mallory), squat)
    assert client.data_query(record.id, owner=mallory.eoa_address).digest == squat.digest

    with django_capture_on_commit_callbacks(execute=True):
        for queued in anchoring:
            queued()
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    on_chain = client.data_query(record.id, owner=alice.owner.eoa_address)
    assert on_chain.digest.hex() == record.digest
    verdict = records_verify(record_ids=[record.id], viewer_id=alice.owner.pk)[0].verdict
    assert verdict.outcome == Verdict.Outcome.VERIFIED
    assert not SecurityEvent.objects.filter(record=record).exists()
