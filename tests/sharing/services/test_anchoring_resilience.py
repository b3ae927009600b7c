"""The anchoring and grant services when the chain misbehaves: outages, lost answers,
confirmations not reached yet, and refusals that will never change."""

from collections.abc import Callable

import pytest

from accounts.models import ChainState
from accounts.selectors import owner_eoa_account
from chainworker.errors import ChainUnavailable, TransactionDropped, TransactionReverted
from chainworker.work import CHAIN_TASK, ChainWorkNotReady
from core.redis_client import get_redis, redis_key
from sharing.models import Grant, Record
from sharing.services import anchoring
from sharing.services.anchoring import anchor_item, records_anchor
from sharing.services.grant_chain import grant_sync_on_chain
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create
from tests.support.anvil_rpc import blocks_mine

pytestmark = [pytest.mark.django_db, pytest.mark.usefixtures("records_mode")]


@pytest.fixture
def scheduled(monkeypatch) -> list[tuple[int, float | None]]:
    """Runs queued by the anchoring service, instead of running them inline (eager mode)."""
    queued: list[tuple[int, float | None]] = []
    monkeypatch.setattr(
        anchoring,
        "enqueue",
        lambda path, *args, countdown=None: queued.append((args[0], countdown)) or True,
    )
    return queued


def _pending(setup, count: int) -> list[Record]:
    return [record_create(robot=setup.robot, data=setup.seal(seq)) for seq in range(1, count + 1)]


def _uploads(deployed) -> int:
    return len(deployed.events(names=["DataUploaded"]))


def test_an_outage_longer_than_max_attempts_gives_nothing_up(
    make_robot, deployed, settings, monkeypatch, scheduled
):
    setup = make_robot()
    records = _pending(setup, 3)
    real_send = deployed.data_upload_batch

    def node_away(*args, **kwargs):
        raise ChainUnavailable("chain node unreachable: connection refused")

    monkeypatch.setattr(deployed, "data_upload_batch", node_away)
    for _ in range(settings.ANCHOR_MAX_ATTEMPTS + 3):
        with pytest.raises(ChainUnavailable):
            records_anchor(owner_id=setup.owner.pk)
    assert set(Record.objects.values_list("status", "anchor_attempts")) == {
        (Record.Status.PENDING, 0)
    }

    monkeypatch.setattr(deployed, "data_upload_batch", real_send)
    assert records_anchor(owner_id=setup.owner.pk) == len(records)
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}


def test_a_batch_that_reached_the_node_before_its_answer_was_lost_is_settled_at_once(
    make_robot, deployed, monkeypatch, scheduled
):
    """The send arrived, the answer did not: the next run's send is refused (RecordExists)
    and the whole batch is settled from the chain in that run, each record anchored once."""
    setup = make_robot()
    _pending(setup, 5)
    real_send = deployed.data_upload_batch

    def sent_then_lost(account, items, *, wait):
        real_send(account, items, wait=True)
        raise ChainUnavailable("chain node unreachable: read timed out")

    monkeypatch.setattr(deployed, "data_upload_batch", sent_then_lost)
    with pytest.raises(ChainUnavailable):
        records_anchor(owner_id=setup.owner.pk)
    monkeypatch.setattr(deployed, "data_upload_batch", real_send)

    records_anchor(owner_id=setup.owner.pk)
    anchored = Record.objects.filter(status=Record.Status.ANCHORED)
    assert anchored.count() == 5
    assert all(record.tx_hash.startswith("0x") and record.block_number for record in anchored)
    assert _uploads(deployed) == 5


def test_records_found_on_chain_wait_for_their_confirmations(make_robot, deployed, scheduled):
    setup = make_robot()
    records = _pending(setup, 2)
    # An earlier run sent them and died before writing down the receipt.
    deployed.data_upload_batch(owner_eoa_account(setup.owner), [anchor_item(r) for r in records])
    Record.objects.update(anchor_attempts=1)
    deployed.confirmations = 2
    scheduled.clear()

    assert records_anchor(owner_id=setup.owner.pk) == 0
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.PENDING}
    assert _uploads(deployed) == 2  # not sent again either
    assert scheduled == [(setup.owner.pk, anchoring.ANCHOR_RECHECK_DELAY)]  # look again later

    blocks_mine(deployed.url, 2)
    records_anchor(owner_id=setup.owner.pk)
    assert set(Record.objects.values_list("status", flat=True)) == {Record.Status.ANCHORED}
    assert _uploads(deployed) == 2


def test_a_grant_the_contract_refuses_for_good_fails_instead_of_retrying_forever(
    make_owner, deployed, monkeypatch, django_capture_on_commit_callbacks
):
    alice, bob = make_owner("alice"), make_owner("bob")

    def refused(*args, **kwargs):
        raise TransactionReverted("GranteeNotRegistered", {"grantee": bob.eoa_address})

    monkeypatch.setattr(deployed, "authority_grant", refused)
    with django_capture_on_commit_callbacks(execute=True):
        grant = grant_create(owner=alice, grantee=bob)
    grant.refresh_from_db()
    assert grant.status == Grant.Status.FAILED
    assert "GranteeNotRegistered" in grant.failure_reason
    assert not deployed.has_access(alice.eoa_address, bob.eoa_address)


def test_a_refused_revocation_is_never_given_up(
    make_owner, deployed, monkeypatch, django_capture_on_commit_callbacks
):
    alice, bob = make_owner("alice"), make_owner("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice, grantee=bob)

    def refused(*args, **kwargs):
        raise TransactionReverted("NotRegistered", {"caller": alice.eoa_address})

    monkeypatch.setattr(deployed, "authority_revoke", refused)
    grant = grant_revoke(owner=alice, grantee=bob)
    with pytest.raises(TransactionReverted):
        grant_sync_on_chain(grant_id=grant.pk)
    grant.refresh_from_db()
    assert grant.status == Grant.Status.REVOKING  # still to do; the sweep will retry


def test_a_grant_waits_for_both_owners_to_be_registered(make_owner, deployed):
    alice, bob = make_owner("alice"), make_owner("bob")
    type(bob).objects.filter(pk=bob.pk).update(chain_state=ChainState.PENDING)
    grant = Grant.objects.create(owner=alice, grantee=bob)
    with pytest.raises(ChainWorkNotReady, match="not registered on chain yet"):
        grant_sync_on_chain(grant_id=grant.pk)
    assert Grant.objects.get(pk=grant.pk).status == Grant.Status.PENDING


def _committed_uploads(setup, capture_on_commit) -> Callable[[int], None]:
    """upload(seq): the robot's upload of `seq`, with what runs after its commit."""

    def upload(seq: int) -> None:
        with capture_on_commit(execute=True):
            record_create(robot=setup.robot, data=setup.seal(seq))

    return upload


def test_uploads_while_a_run_works_queue_no_second_run(
    make_robot, monkeypatch, scheduled, django_capture_on_commit_callbacks
):
    """The "a run is queued" flag stays set while the run works: uploads meanwhile queue
    nothing (their records go in this run, or the one it queues), and it is dropped after."""
    setup = make_robot()
    scheduled.clear()  # the run queued once the owner was registered
    upload = _committed_uploads(setup, django_capture_on_commit_callbacks)

    upload(1)
    assert len(scheduled) == 1
    monkeypatch.setattr(anchoring, "_wait_for_batch_to_fill", lambda owner_id: upload(2))
    assert records_anchor(owner_id=setup.owner.pk) == 2
    assert len(scheduled) == 1  # the upload during the run queued nothing
    upload(3)
    assert len(scheduled) == 2  # the flag was dropped when the run ended

    def broken(owner_id: int) -> None:
        raise ValueError("a bug")

    monkeypatch.setattr(anchoring, "_wait_for_batch_to_fill", broken)
    with pytest.raises(ValueError, match="a bug"):
        records_anchor(owner_id=setup.owner.pk)
    upload(4)
    assert len(scheduled) == 3  # a run that failed for good drops the flag too


@pytest.mark.parametrize(
    "outage",
    [
        ChainUnavailable("chain node unreachable"),
        ChainWorkNotReady("the chain was reset"),
        TransactionDropped("0x01", "the node does not hold it"),
    ],
)
def test_uploads_while_a_failed_run_waits_for_its_retry_queue_no_run_of_their_own(
    make_robot, monkeypatch, scheduled, django_capture_on_commit_callbacks, outage
):
    """A run that failed for a transient reason is retried by its task: during an outage the
    uploads wait for that one run (each queueing a retrying run of its own piled up thousands
    in an hour). The flag lapses after the longest retry backoff and a margin, so a retry lost
    with its worker leaves the owner to the next upload or the sweep."""
    setup = make_robot()
    scheduled.clear()  # the run queued once the owner was registered
    upload = _committed_uploads(setup, django_capture_on_commit_callbacks)

    upload(1)
    assert len(scheduled) == 1

    def away(owner_id: int) -> None:
        raise outage

    monkeypatch.setattr(anchoring, "_wait_for_batch_to_fill", away)
    with pytest.raises(type(outage)):
        records_anchor(owner_id=setup.owner.pk)
    for seq in range(2, 12):
        upload(seq)
    assert len(scheduled) == 1
    flag = redis_key("anchor-scheduled", setup.owner.pk)
    lapses = CHAIN_TASK["retry_backoff_max"] + anchoring.RETRY_FLAG_MARGIN
    assert CHAIN_TASK["retry_backoff_max"] < get_redis().ttl(flag) <= lapses
    get_redis().delete(flag)  # as when it lapses
    upload(12)
    assert len(scheduled) == 2
