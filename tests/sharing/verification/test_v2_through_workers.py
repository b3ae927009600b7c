"""Provenance v2 with the portal's real processes (gunicorn, a Celery worker, beat, anvil): a
paired robot's batch signed once is uploaded over HTTP, anchored by the worker, and read
through the worker's check by its owner and a grantee, its proof carrying the batch and the
topic_seq; a changed record and a reused topic_seq are refused whole over HTTP."""

import base64
import uuid

import pytest
import requests

from accounts.models import ChainState, Owner
from accounts.services.owners import owner_create
from sharing.models import Grant, Record, SecurityEvent
from sharing.services.grants import grant_create
from smcrypto import envelope, sm4
from tests.support.batches import batch_sealed, batch_signed, seal_batch
from tests.support.harness import wait_for
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup
from tests.support.worker_robots import paired_robot, registered_robots

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]


def _post(url: str, setup: RobotSetup, envelopes: list[bytes]) -> requests.Response:
    return requests.post(
        f"{url}/api/v1/records/",
        json={"envelopes": [base64.b64encode(data).decode() for data in envelopes]},
        headers={"Authorization": f"Token {setup.token}"},
        timeout=60,
    )


def test_a_v2_batch_through_the_real_processes(worker_stack, make_owner_token):
    stack = worker_stack(workers=1)
    url = stack.start_web(workers=1)
    (alice,) = registered_robots(1)
    setup = paired_robot(alice.owner, alice.key)
    bob = owner_create(
        username=f"bob-{uuid.uuid4().hex[:6]}", password=TEST_PASSWORD, sm4_key=sm4.generate_key()
    )
    wait_for(
        lambda: Owner.objects.get(pk=bob.pk).chain_state == ChainState.CONFIRMED,
        timeout=120,
        what="the grantee registered on chain",
    )
    bob.refresh_from_db()
    grant = grant_create(owner=setup.owner, grantee=bob)
    wait_for(
        lambda: Grant.objects.get(pk=grant.pk).status == Grant.Status.ACTIVE,
        timeout=120,
        what="the grant confirmed on chain",
    )

    answer = _post(url, setup, seal_batch(setup, [1, 2, 3, 4], topic_seqs=[0, 1, 2, 3]))
    assert answer.status_code == 201, answer.text
    ids = [result["id"] for result in answer.json()]
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == 4,
        timeout=120,
        what="the batch anchored by the worker",
    )
    assert list(Record.objects.order_by("seq").values_list("topic_seq", flat=True)) == [0, 1, 2, 3]

    for viewer in (setup.owner, bob):
        _token, key = make_owner_token(viewer, scopes=("read",))
        headers = {"Authorization": f"Token {key}"}
        roots = set()
        for index, record_id in enumerate(ids):
            content = requests.get(
                f"{url}/api/v1/records/{record_id}/content/", headers=headers, timeout=60
            )
            assert content.status_code == 200, content.text
            proof = requests.get(
                f"{url}/api/v1/records/{record_id}/proof/", headers=headers, timeout=60
            ).json()
            assert proof["topic_seq"] == index
            assert (proof["batch"]["sig_index"], proof["batch"]["sig_size"]) == (index, 4)
            header = envelope.read_header(base64.b64decode(proof["envelope"])).header
            assert header["sig_path"] == proof["batch"]["sig_path"]
            roots.add(proof["batch"]["root"])
        assert len(roots) == 1

    signed = batch_signed(setup, [5, 6], topic_seqs=[4, 5])
    signed[0] = (signed[0][0], b'{"K": {"changed": true}}')
    refused = _post(url, setup, batch_sealed(setup, signed))
    assert (refused.status_code, refused.json()["error"]) == (403, "signature_refused")
    reused = _post(url, setup, seal_batch(setup, [5, 6], topic_seqs=[4, 2]))
    assert (reused.status_code, reused.json()["error"]) == (409, "topic_seq_reused")
    assert Record.objects.count() == 4
    kinds = sorted(SecurityEvent.objects.values_list("kind", flat=True))
    assert kinds == [SecurityEvent.Kind.BAD_SIGNATURE, SecurityEvent.Kind.TOPIC_SEQ_REUSED]
