"""A record's robot signature facts, written once (sharing.verification.signature): the proof
answer and the export's bundle state the same signer, signature and public key, the key as
`04||x||y` lowercase hex, the form authros_verify checks."""

import pytest

from chainworker.services import chain_client
from sharing.cache import envelope_fetch
from sharing.models import Record
from sharing.verification.signature import record_signature, signature_facts
from smcrypto import envelope, sm2

pytestmark = pytest.mark.django_db


def test_the_proof_states_the_facts_the_bundle_states(make_paired_robot, upload):
    setup = make_paired_robot("alice")
    record = upload(setup, 1)
    assert record.status == Record.Status.ANCHORED
    data, _source = envelope_fetch(record)
    header, _plaintext = envelope.open(setup.key, data)
    facts = signature_facts(record, header)
    assert facts == {
        "signer": record.signer,
        "public_key": sm2.public_key_normalize(setup.robot.public_key),
        "sig": header["sig"],
    }
    assert facts["public_key"] == facts["public_key"].lower()
    assert facts["public_key"].startswith("04")
    assert len(facts["public_key"]) == 130
    proof = record_signature(record, data, chain_client())
    assert {name: proof[name] for name in facts} == facts
    assert proof["key_owner"].lower() == setup.owner.eoa_address.lower()


def test_an_unsigned_record_has_no_signature_facts(make_robot, upload):
    setup = make_robot("alice")
    record = upload(setup, 1)
    data, _source = envelope_fetch(record)
    assert signature_facts(record, envelope.read_header(data).header) is None
    assert record_signature(record, data, chain_client()) is None
