"""What one view costs in each process (issue 43): the record row read once, each SM4 key
unwrapped once and the envelope decrypted once in the web process, and the same in the
worker's check (which decrypts a signed envelope to check its robot signature; the plaintext
never leaves it: it hands back the envelope it checked). Counted with spies on the real
functions, tagged by whether the worker's check is running, so that a second read, unwrap or
decryption in either process fails here."""

import re
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
from django.db import connection
from django.urls import reverse

from sharing.models import Record
from sharing.services.grants import grant_create
from sharing.verification import check, keys
from smcrypto import envelope
from tests.api.conftest import session_client

pytestmark = pytest.mark.django_db

_RECORD_ROWS = re.compile(r'FROM "?sharing_record"?(\s|$)')


@dataclass
class Costs:
    """What each process did during one view: "web" or "worker"."""

    in_worker: bool = False
    record_reads: Counter = field(default_factory=Counter)
    unwraps: dict[str, list[tuple[int, str]]] = field(
        default_factory=lambda: {"web": [], "worker": []}
    )
    decryptions: Counter = field(default_factory=Counter)

    @property
    def side(self) -> str:
        return "worker" if self.in_worker else "web"


@pytest.fixture
def costs(monkeypatch) -> Iterator[Costs]:
    counted = Costs()
    real_verify, real_unwrap, real_open = (
        check.records_verify,
        keys.owner_key_bytes,
        envelope.OpeningKey.open,
    )

    def verify(**kwargs):
        counted.in_worker = True
        try:
            return real_verify(**kwargs)
        finally:
            counted.in_worker = False

    def unwrap(owner_key):
        counted.unwraps[counted.side].append((owner_key.owner_id, owner_key.key_id))
        return real_unwrap(owner_key)

    def decrypt(opening, data, **kwargs):  # envelope.open opens through an OpeningKey too
        counted.decryptions[counted.side] += 1
        return real_open(opening, data, **kwargs)

    def queries(execute, sql, params, many, context):
        if sql.lstrip().upper().startswith("SELECT") and _RECORD_ROWS.search(sql):
            counted.record_reads[counted.side] += 1
        return execute(sql, params, many, context)

    monkeypatch.setattr(check, "records_verify", verify)
    monkeypatch.setattr(keys, "owner_key_bytes", unwrap)
    monkeypatch.setattr(envelope.OpeningKey, "open", decrypt)
    with connection.execute_wrapper(queries):
        yield counted


@pytest.fixture
def signed(make_paired_robot, make_owner, upload, django_capture_on_commit_callbacks):
    """alice's signed, anchored record, shared with bob."""
    setup = make_paired_robot("alice")
    record = upload(setup, 1)
    assert record.signer
    assert record.status == Record.Status.ANCHORED
    bob = make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=setup.owner, grantee=bob)
    return setup, bob, record


def _each_once(unwrapped: list[tuple[int, str]]) -> bool:
    return len(unwrapped) == len(set(unwrapped))


def test_a_grantees_content_view_reads_unwraps_and_decrypts_once_in_each_process(signed, costs):
    setup, bob, record = signed
    answer = session_client(bob).get(f"/api/v1/records/{record.pk}/content/")
    assert answer.status_code == 200, answer.content
    assert costs.record_reads == {"web": 1, "worker": 1}
    assert costs.decryptions == {"web": 1, "worker": 1}
    # The web: alice's key to open, bob's own to re-seal; the worker: alice's to check.
    assert sorted(costs.unwraps["web"]) == sorted(
        [(setup.owner.pk, record.key_id), (bob.pk, bob.keys.get(is_current=True).key_id)]
    )
    assert costs.unwraps["worker"] == [(setup.owner.pk, record.key_id)]


def test_an_owners_content_view_unwraps_their_key_once_for_opening_and_resealing(signed, costs):
    setup, _bob, record = signed
    answer = session_client(setup.owner).get(f"/api/v1/records/{record.pk}/content/")
    assert answer.status_code == 200, answer.content
    assert costs.unwraps == {
        "web": [(setup.owner.pk, record.key_id)],
        "worker": [(setup.owner.pk, record.key_id)],
    }
    assert costs.decryptions == {"web": 1, "worker": 1}
    assert costs.record_reads == {"web": 1, "worker": 1}


def test_a_record_page_reads_unwraps_and_decrypts_once_in_each_process(signed, costs, client):
    setup, bob, record = signed
    client.force_login(bob.user)
    assert client.get(reverse("record-detail", args=[record.pk])).status_code == 200
    assert costs.decryptions == {"web": 1, "worker": 1}
    assert _each_once(costs.unwraps["web"])
    assert _each_once(costs.unwraps["worker"])
    assert costs.unwraps["worker"] == [(setup.owner.pk, record.key_id)]
    assert costs.record_reads["worker"] == 1
