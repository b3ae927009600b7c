"""The check of v2 records (DESIGN.md "Provenance v2"): each distinct batch signature verified
once per check, however many of its records are read; v1 records still one each. Counted
where the check verifies (smcrypto.sm2.verify_many), against the session's anvil."""

import pytest

from sharing.models import Record, Verdict
from sharing.services.uploads import record_create_batch
from sharing.verification.check import records_verify
from tests.support.batches import seal_batch

pytestmark = pytest.mark.django_db


def _stored(setup, envelopes, capture) -> list[Record]:
    with capture(execute=True):
        records = record_create_batch(robot=setup.robot, envelopes=envelopes)
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}
    return records


def test_a_check_of_fifty_records_of_one_batch_verifies_one_signature(
    make_paired_robot, verifications, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    envelopes = seal_batch(setup, range(1, 51), topic_seqs=range(50))
    records = _stored(setup, envelopes, django_capture_on_commit_callbacks)
    verifications.clear()
    checked = records_verify(record_ids=[r.id for r in records], viewer_id=setup.owner.pk)
    assert [c.verdict.outcome for c in checked] == [Verdict.Outcome.VERIFIED] * 50
    assert sum(verifications) == 1
    assert all(c.envelope is not None for c in checked)


def test_a_check_verifies_each_batch_once_and_each_v1_record_once(
    make_paired_robot, verifications, django_capture_on_commit_callbacks
):
    setup = make_paired_robot("alice")
    _stored(
        setup,
        seal_batch(setup, range(1, 11), topic_seqs=range(10)),
        django_capture_on_commit_callbacks,
    )
    _stored(
        setup,
        seal_batch(setup, range(11, 21), topic_seqs=range(10, 20)),
        django_capture_on_commit_callbacks,
    )
    _stored(setup, [setup.seal(seq) for seq in (21, 22, 23)], django_capture_on_commit_callbacks)
    ids = list(Record.objects.order_by("seq").values_list("pk", flat=True))
    verifications.clear()
    checked = records_verify(record_ids=ids, viewer_id=setup.owner.pk)
    assert [c.verdict.outcome for c in checked] == [Verdict.Outcome.VERIFIED] * 23
    assert sum(verifications) == 2 + 3
