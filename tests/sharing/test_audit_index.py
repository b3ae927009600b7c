"""The audit page reads the database's index of owners' transactions (F8), written when the
worker sees each receipt: paged, with times, for the owner and the grantee, and without one
call to the chain. The backfill migration builds the same index from what the database held."""

import importlib
import re
from datetime import UTC, datetime, timedelta

import pytest
from django.apps import apps
from django.db import connection
from django.test.utils import CaptureQueriesContext
from django.urls import reverse

from accounts.models import ChainActivity
from accounts.services.activity import chain_activity_record
from accounts.services.keys import key_rotate
from chainworker import services as chain_services
from sharing.models import Grant, Record
from sharing.services.uploads import record_create_batch
from smcrypto import sm4
from stack.anvil import free_port

pytestmark = pytest.mark.django_db

NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
TX_HASH = r'transaction <span class="hash">(0x[0-9a-f]{64})</span>'

backfill = importlib.import_module("accounts.migrations.0004_chain_activity_backfill")


def _kinds(html: str) -> list[str]:
    return re.findall(r'data-kind="([\w-]+)" data-testid="audit-entry"', html)


@pytest.fixture
def history(client, make_robot, make_owner, upload, django_capture_on_commit_callbacks):
    """alice registered, uploaded twice (two anchoring transactions), rotated her key, granted
    bob access and revoked it, through the pages and the worker's tasks (run inline)."""
    alice = make_robot("alice")
    bob = make_owner("bob")
    upload(alice, 1)
    upload(alice, 2)
    with django_capture_on_commit_callbacks(execute=True):
        key_rotate(owner=alice.owner, sm4_key=sm4.generate_key())
    client.force_login(alice.owner.user)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grants"), {"grantee": "bob", "confirm_all": "True"})
    with django_capture_on_commit_callbacks(execute=True):
        client.post(reverse("grant-revoke"), {"grantee": "bob"})
    assert Grant.objects.get(owner=alice.owner, grantee=bob).status == Grant.Status.REVOKED
    return alice, bob


@pytest.fixture
def no_chain(monkeypatch, settings):
    """Every way to the chain fails from here on."""

    def unreachable(*args, **kwargs):
        raise AssertionError("the audit page must not call the chain")

    monkeypatch.setattr(chain_services, "chain_client", unreachable)
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    chain_services._clients.clear()


def test_the_audit_page_lists_the_index_with_times_for_owner_and_grantee(client, history, no_chain):
    alice, bob = history
    owner = alice.owner
    client.force_login(owner.user)
    page = client.get(reverse("audit"))
    html = page.content.decode()
    assert page.status_code == 200
    kinds = _kinds(html)
    # Grants, revocations and key changes first, then the anchoring, a minute a line.
    assert kinds[:3] == ["revoke-given", "grant-given", "key_rotated"]
    assert kinds[3:5] == ["registered", "enrolled"]
    not_anchoring = ChainActivity.objects.filter(owner=owner).exclude(kind="anchored").count()
    assert kinds[:not_anchoring][-1] in ("enrolled", "funded")
    assert set(kinds[not_anchoring:]) == {"upload"}
    assert "Revoked access to bob" in html
    assert "Granted access to bob" in html
    account = html.split('id="audit-anchoring"')[0]
    times = re.findall(r'data-testid="audit-time">(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) UTC', account)
    assert len(times) == not_anchoring
    assert times == sorted(times, reverse=True)
    owner.refresh_from_db()
    assert owner.register_tx in html
    assert owner.enroll_tx in html
    assert f"Block {owner.registered_block}" in html
    for record in Record.objects.filter(owner=owner):
        assert record.tx_hash in html
        assert reverse("record-detail", args=[record.id]) in html
    grant = Grant.objects.get(owner=owner, grantee=bob)
    assert grant.grant_tx in html
    assert grant.revoke_tx in html

    client.force_login(bob.user)
    received = client.get(reverse("audit")).content.decode()
    assert _kinds(received)[:2] == ["revoke-received", "grant-received"]
    assert "alice revoked your access" in received
    assert "alice granted you access" in received
    assert grant.revoke_tx in received
    assert owner.register_tx not in received
    assert "upload" not in _kinds(received)


def test_the_audit_page_is_paged_in_the_database(client, history, no_chain, monkeypatch):
    """Minutes of anchoring are paged; grants, revocations and keys stay on top of each."""
    monkeypatch.setattr("sharing.views.audit.AUDIT_ENTRIES_PER_PAGE", 1)
    alice, _bob = history
    rows = ChainActivity.objects.filter(owner=alice.owner, kind="anchored").order_by("id")
    for row, minute in zip(rows, (1, 2), strict=True):
        ChainActivity.objects.filter(pk=row.pk).update(
            at=datetime(2026, 3, 1, 12, minute, tzinfo=UTC)
        )
    client.force_login(alice.owner.user)
    first = client.get(reverse("audit")).content.decode()
    second = client.get(reverse("audit"), {"page": 2})
    assert second.status_code == 200
    assert "Page 1 of 2" in first
    assert "Page 2 of 2" in second.content.decode()
    assert "Anchored 1 record in 12:02 (UTC)" in first
    assert "Anchored 1 record in 12:01 (UTC)" in second.content.decode()
    assert first.count('data-kind="upload"') == 1
    firsts = set(re.findall(TX_HASH, first))
    seconds = set(
        re.findall(
            r'transaction <span class="hash">(0x[0-9a-f]{64})</span>', second.content.decode()
        )
    )
    assert "Revoked access to bob" in first
    assert "Revoked access to bob" in second.content.decode()
    assert rows[1].tx_hash in firsts
    assert rows[0].tx_hash not in firsts
    assert rows[0].tx_hash in seconds
    assert client.get(reverse("audit"), {"page": "junk"}).status_code == 200
    assert client.get(reverse("audit"), {"page": 10**30}).status_code == 200


def test_an_anchoring_entry_lists_its_first_records_read_in_one_query(
    client, make_robot, monkeypatch, django_capture_on_commit_callbacks
):
    monkeypatch.setattr("sharing.audit.AUDIT_RECORDS_PER_UPLOAD", 2)
    alice = make_robot("alice")
    for seqs in ((1, 2, 3), (4,), (5, 6)):
        with django_capture_on_commit_callbacks(execute=True):
            record_create_batch(robot=alice.robot, envelopes=[alice.seal(seq) for seq in seqs])
    anchored = ChainActivity.objects.filter(owner=alice.owner, kind="anchored").order_by("id")
    assert list(anchored.values_list("record_count", flat=True)) == [3, 1, 2]
    for row, minute in zip(anchored, (1, 2, 3), strict=True):  # three minutes, three lines
        ChainActivity.objects.filter(pk=row.pk).update(
            at=datetime(2026, 3, 1, 12, minute, tzinfo=UTC)
        )
    client.force_login(alice.owner.user)
    with CaptureQueriesContext(connection) as queries:
        html = client.get(reverse("audit")).content.decode()
    record_queries = [q for q in queries.captured_queries if 'FROM "sharing_record"' in q["sql"]]
    assert len(record_queries) == 1
    assert "Anchored 3 records in 12:01 (UTC)" in html
    assert "Anchored 1 record in 12:02 (UTC)" in html
    assert "and 1 more" in html
    first = Record.objects.get(owner=alice.owner, seq=1)
    assert reverse("record-detail", args=[first.id]) in html
    assert reverse("record-detail", args=[Record.objects.get(seq=3).id]) not in html


def test_a_retried_receipt_writes_no_second_row(history):
    alice, _bob = history
    row = ChainActivity.objects.filter(owner=alice.owner, kind="anchored").first()
    again = chain_activity_record(
        owner=alice.owner,
        kind="anchored",
        tx_hash=row.tx_hash,
        block_number=row.block_number,
        record_count=row.record_count,
    )
    assert again.pk == row.pk
    assert again.at == row.at
    assert ChainActivity.objects.filter(tx_hash=row.tx_hash).count() == 1


def _index() -> set[tuple]:
    """The index's rows, less what the database does not keep (the blocks of funding and
    enrolment, the exact times)."""
    return {
        (
            row.owner_id,
            row.counterpart_id,
            row.kind,
            row.tx_hash,
            None if row.kind in ("funded", "enrolled") else row.block_number,
            row.record_count,
            tuple(sorted(row.detail.items())),
        )
        for row in ChainActivity.objects.all()
    }


def test_the_backfill_builds_the_same_index_from_the_database(history):
    written = _index()
    assert {kind for _, _, kind, *_ in written} >= {
        "enrolled",
        "registered",
        "key_rotated",
        "anchored",
        "granted",
        "revoked",
    }
    ChainActivity.objects.all().delete()
    backfill.chain_activity_backfill(apps, None)
    assert _index() == written
    backfill.chain_activity_backfill(apps, None)  # run again: nothing doubles
    assert _index() == written
    assert ChainActivity.objects.count() == len(written)


def test_anchoring_once_a_second_is_one_line_a_minute_under_the_grants(
    client, make_robot, make_owner
):
    """60 anchoring transactions of 12 records in the minute 12:04 make one line, "Anchored
    720 records in 12:04 (UTC)"; a grant older than all of them is still listed above."""
    alice = make_robot("alice")
    bob = make_owner("bob")
    ChainActivity.objects.create(
        owner=alice.owner,
        counterpart=bob,
        kind="granted",
        tx_hash="0x" + "ab" * 32,
        block_number=5,
        at=NOON - timedelta(days=1),
    )
    for second in range(60):
        ChainActivity.objects.create(
            owner=alice.owner,
            kind="anchored",
            tx_hash=f"0x{second:064x}",
            block_number=100 + second,
            record_count=12,
            at=NOON.replace(minute=4, second=second),
        )
    ChainActivity.objects.create(
        owner=alice.owner,
        kind="anchored",
        tx_hash="0x" + "cd" * 32,
        block_number=200,
        record_count=1,
        at=NOON.replace(minute=5, second=1),
    )
    client.force_login(alice.owner.user)
    html = client.get(reverse("audit")).content.decode()
    kinds = _kinds(html)
    assert kinds.index("grant-given") < kinds.index("upload")
    assert kinds.count("upload") == 2
    assert html.index("Granted access to bob") < html.index("Anchored 720 records")
    assert "Anchored 720 records in 12:04 (UTC)" in html
    assert "Anchored 1 record in 12:05 (UTC)" in html
    assert "Blocks 100\u2013159" in html
    assert "60 transactions" in html
    assert "and 57 more" in html  # three transactions named
    assert html.index("12:05 (UTC)") < html.index("12:04 (UTC)")  # newest first
