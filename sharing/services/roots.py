"""Anchoring by Merkle roots (ANCHOR_MODE=root, DESIGN.md "Anchoring by Merkle roots").

A run builds SM3 trees (smcrypto.merkle) over an owner's pending records, oldest first, at most
ANCHOR_ROOT_MAX leaves each, and sends each root with `anchorRoot` from the owner's EOA: one
transaction, about 55k gas, whatever the number of records under it. A tree holds one owner's
records and is sent by that owner's account, so the chain itself says whose records they are
(docs/architecture.md). The tree is written to the database before it is sent: the AnchorRoot
row (root, size, the sender's previous root, the record ids in leaf order), and per record its
leaf index and audit path.

Exactly once: a sender's roots are chained on chain (`prevRoot` must be the sender's last
root), so of two trees sent after the same root at most one can land. A tree sent earlier
and not on chain is sent again, the same root after the same previous root, while it still
can land; once the sender's last root on chain has moved past its previous root it never can,
and its records go into a new tree.

Records signed by a robot key not on chain yet go into no tree (AWAITING_ROBOT_KEY); a tree
to send again that holds some (after a chain reset) waits for the key, and the trees after it
with it, so that it is sent again as it was.
"""

import logging
import time
from collections.abc import Sequence

from django.conf import settings
from django.db import connections, transaction
from django.db.models import F
from django.utils import timezone
from eth_account.signers.local import LocalAccount
from redis.lock import Lock

from accounts.models import ChainActivity, Owner
from accounts.selectors import owner_eoa_account
from accounts.services.activity import chain_activity_record
from chainworker.client import AuthROSChain
from chainworker.errors import (
    ChainUnavailable,
    InsufficientFunds,
    TransactionDropped,
    TransactionReverted,
    TransactionTimeout,
)
from chainworker.services import chain_stall_check
from core.locks import lock_renew
from sharing.models import AnchorRoot, Record
from sharing.services.anchor_wait import (
    AWAITING_ROBOT_KEY,
    gas_wait_end,
    gas_wait_start,
    receipt_await,
    records_fail_exhausted,
)
from smcrypto.merkle import MerkleTree, leaf_hash, path_split

logger = logging.getLogger("sharing.services.anchoring")


def roots_anchor_round(client: AuthROSChain, owner: Owner, lock: Lock) -> tuple[int, int]:
    """One run's trees, sends and receipts for an owner; (records anchored, roots sent)."""
    account = owner_eoa_account(owner)
    tip, again = _settle_sent(client, owner, account.address)
    in_flight: list[tuple[AnchorRoot, str]] = []
    refusal: TransactionReverted | None = None
    cannot_pay: InsufficientFunds | None = None
    for _ in range(settings.ANCHOR_INFLIGHT):
        if not lock_renew(lock):
            break
        resent = bool(again)
        tree = again.pop(0) if again else _tree_next(owner, account.address, tip)
        if tree is None or (resent and _awaits_robot_key(tree)):
            break
        try:
            # Only the first root of a run follows a root on chain: the others follow one still
            # in flight, which an estimate against the latest block would refuse.
            tx_hash = _send(client, account, tree, estimate=not in_flight)
        except InsufficientFunds as exc:
            pending = Record.objects.filter(owner_id=owner.pk, status=Record.Status.PENDING)
            gas_wait_start(
                owner.pk, pending.exclude(anchor_root__in=[sent for sent, _tx in in_flight])
            )
            cannot_pay = exc
            break
        except TransactionReverted as exc:
            if exc.error_name == "WrongPrevRoot":
                # Another tree landed after the same root (a run we lost track of): this one
                # never can. Its records go into a new tree after the chain's last root.
                _tree_dropped(tree)
            elif exc.error_name != "RootExists":  # RootExists: on chain already, settled next
                refusal = exc
            break
        if not in_flight:
            gas_wait_end(owner.pk)
        in_flight.append((tree, tx_hash))
        tip = tree.root
        if not resent and tree.size < settings.ANCHOR_ROOT_MAX:
            # The backlog fitted in a new tree: records that arrived since wait for the next
            # run (a tree of their own after ANCHOR_MAX_WAIT), not a transaction each for the
            # few that came in while this one was built and sent.
            break
    anchored = 0
    for position, (tree, tx_hash) in enumerate(in_flight):
        try:
            receipt = receipt_await(client, tx_hash, lock)
        except TransactionReverted as exc:
            # A root sent after one in flight, refused once mined (that one did not land, or
            # another root did first): this and the rest are settled by the next run.
            logger.warning("root %s of %s refused on chain: %s", tree.root, owner, exc)
            break
        except TransactionTimeout:
            if chain_stall_check(since=time.time() - client.receipt_timeout).stalled:
                # As in records mode: a stalled chain is not these records' fault.
                _attempts_return([waiting for waiting, _tx in in_flight[position:]])
            raise
        except TransactionDropped:
            # The node lost it (restarted without it, or lost its latest blocks): not the
            # records' fault either. The next run sends the tree again, counting nonces from
            # the node.
            _attempts_return([waiting for waiting, _tx in in_flight[position:]])
            raise
        anchored += _tree_anchored(tree, tx_hash=tx_hash, block=int(receipt["blockNumber"]))
    if refusal is not None:
        raise refusal
    if cannot_pay is not None:
        raise cannot_pay
    return anchored, len(in_flight)


def _send(client: AuthROSChain, account: LocalAccount, tree: AnchorRoot, *, estimate: bool) -> str:
    """Send the tree's root (an attempt for each of its records); its transaction hash."""
    _attempts_count(tree)
    try:
        tx_hash = client.anchor_root(
            account,
            bytes.fromhex(tree.root),
            tree.size,
            bytes.fromhex(tree.prev_root),
            wait=False,
            estimate=estimate,
        )
    except (ChainUnavailable, InsufficientFunds):
        # An outage (the node, Redis, the owner's gas), not the records' fault: no attempt.
        _attempts_return([tree])
        raise
    AnchorRoot.objects.filter(pk=tree.pk).update(tx_hash=tx_hash)
    return tx_hash


def _settle_sent(client: AuthROSChain, owner: Owner, sender: str) -> tuple[str, list[AnchorRoot]]:
    """Settle the trees earlier runs sent, oldest first: anchored ones as anchored, those that
    can never land as dropped. Returns the root a new tree follows and the trees to send again
    (lost on the way, and still able to land), in order."""
    _strays_settle(client, owner)
    tip = client.last_root_of(sender).hex()
    again: list[AnchorRoot] = []
    sent = AnchorRoot.objects.filter(owner=owner, status=AnchorRoot.Status.SENT)
    for tree in sent.order_by("created_at", "pk"):
        on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
        if on_chain is not None and on_chain.size == tree.size:
            event = client.root_event(tree.sender, bytes.fromhex(tree.root))
            _tree_anchored(
                tree, tx_hash=event.tx_hash if event else tree.tx_hash, block=on_chain.block_number
            )
            continue
        if tree.prev_root != tip:
            _tree_dropped(tree)  # the sender's chain of roots moved on without it
            continue
        if _exhausted(tree):
            _tree_dropped(tree)  # its records fail in the next batch
            continue
        if not (tree.tx_hash and client.transaction_pending(tree.tx_hash)):
            again.append(tree)  # never reached the node, or the node lost it
        tip = tree.root  # in the node's pool or sent again: the next tree follows it
    return tip, again


def _strays_settle(client: AuthROSChain, owner: Owner) -> None:
    """Pending records in a tree that is not being sent (an operator put them back, or a run
    died between two updates): in an anchored tree still on chain they are anchored again;
    in an anchored tree the chain lacks, the tree is sent again; in a dropped tree they wait
    for a new one."""
    strays = AnchorRoot.objects.filter(
        owner=owner,
        status__in=[AnchorRoot.Status.ANCHORED, AnchorRoot.Status.DROPPED],
        records__status=Record.Status.PENDING,
    ).distinct()
    for tree in strays:
        pending = Record.objects.filter(anchor_root=tree, status=Record.Status.PENDING)
        if tree.status == AnchorRoot.Status.DROPPED:
            pending.update(anchor_root=None, leaf_index=None, merkle_path=b"")
            continue
        on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
        if on_chain is not None and on_chain.size == tree.size:
            pending.update(
                status=Record.Status.ANCHORED,
                tx_hash=tree.tx_hash,
                block_number=tree.block_number,
                anchored_at=timezone.now(),
                failure_reason="",
            )
        else:
            tree_lost(tree)
            AnchorRoot.objects.filter(pk=tree.pk).update(status=AnchorRoot.Status.SENT)


def roots_await_robot_key(owner_id: int) -> bool:
    """Whether a tree of the owner's to send again waits for a robot key (and the owner's later
    trees with it): the key's confirmation queues the run that sends it."""
    return (
        Record.objects.filter(
            owner_id=owner_id,
            status=Record.Status.PENDING,
            anchor_root__status=AnchorRoot.Status.SENT,
        )
        .filter(AWAITING_ROBOT_KEY)
        .exists()
    )


def _awaits_robot_key(tree: AnchorRoot) -> bool:
    pending = Record.objects.filter(anchor_root=tree, status=Record.Status.PENDING)
    return pending.filter(AWAITING_ROBOT_KEY).exists()


def _tree_next(owner: Owner, sender: str, prev_root: str) -> AnchorRoot | None:
    """The next tree of the owner's pending records not in a tree yet and not waiting for
    their robot's key, written before it is sent; None if there are none. Records out of
    attempts are failed first."""
    pending = Record.objects.filter(
        owner_id=owner.pk, status=Record.Status.PENDING, anchor_root__isnull=True
    ).exclude(AWAITING_ROBOT_KEY)
    records_fail_exhausted(owner, pending)
    records = list(
        pending.order_by("created_at", "seq").only("id", "digest")[: settings.ANCHOR_ROOT_MAX]
    )
    if not records:
        return None
    return tree_build(owner=owner, sender=sender, prev_root=prev_root, records=records)


def tree_build(
    *, owner: Owner, sender: str, prev_root: str, records: Sequence[Record]
) -> AnchorRoot:
    """Write the tree over `records` (in this order): its AnchorRoot row, and each record's
    leaf index and audit path."""
    tree = MerkleTree([leaf_hash(sender, r.id, bytes.fromhex(r.digest)) for r in records])
    with transaction.atomic():
        row = AnchorRoot.objects.create(
            owner=owner,
            sender=sender,
            root=tree.root.hex(),
            prev_root=prev_root,
            size=tree.size,
            leaves=b"".join(r.id.bytes for r in records),
        )
        _paths_write(row, records, tree)
    return row


def _paths_write(row: AnchorRoot, records: Sequence[Record], tree: MerkleTree) -> None:
    """Each record's tree, leaf index and audit path: one prepared UPDATE run for every record
    (executemany), not bulk_update's CASE over up to ANCHOR_ROOT_MAX ids."""
    connection = connections[Record.objects.db]
    table = connection.ops.quote_name(Record._meta.db_table)
    columns = [
        connection.ops.quote_name(Record._meta.get_field(name).column)
        for name in ("anchor_root", "leaf_index", "merkle_path", "id")
    ]
    pk = Record._meta.pk
    rows = []
    for index, record in enumerate(records):
        path = b"".join(tree.path(index))
        record.anchor_root, record.leaf_index, record.merkle_path = row, index, path
        rows.append((row.pk, index, path, pk.get_db_prep_value(record.id, connection)))
    assignments = ", ".join(f"{column} = %s" for column in columns[:3])
    # Only the model's own quoted names go into the text; every value is a parameter.
    sql = f"UPDATE {table} SET {assignments} WHERE {columns[3]} = %s"  # noqa: S608
    with connection.cursor() as cursor:
        cursor.executemany(sql, rows)


def _tree_anchored(tree: AnchorRoot, *, tx_hash: str, block: int) -> int:
    """The tree is on chain: it and its pending records are anchored; how many records."""
    now = timezone.now()
    with transaction.atomic():
        AnchorRoot.objects.filter(pk=tree.pk).update(
            status=AnchorRoot.Status.ANCHORED, tx_hash=tx_hash, block_number=block, anchored_at=now
        )
        count = Record.objects.filter(anchor_root=tree, status=Record.Status.PENDING).update(
            status=Record.Status.ANCHORED,
            tx_hash=tx_hash,
            block_number=block,
            anchored_at=now,
            failure_reason="",
        )
    chain_activity_record(
        owner=tree.owner,
        kind=ChainActivity.Kind.ANCHORED,
        tx_hash=tx_hash,
        block_number=block,
        record_count=tree.size,
    )
    return count


def _tree_dropped(tree: AnchorRoot) -> None:
    """The tree can never land: its records wait for a new tree."""
    with transaction.atomic():
        AnchorRoot.objects.filter(pk=tree.pk).update(status=AnchorRoot.Status.DROPPED)
        Record.objects.filter(anchor_root=tree, status=Record.Status.PENDING).update(
            anchor_root=None, leaf_index=None, merkle_path=b""
        )
    logger.info("root %s of %s dropped: its records go into a new tree", tree.root, tree.owner)


def tree_lost(tree: AnchorRoot) -> int:
    """The chain lacks a tree the database says is anchored (lost blocks, a reset chain): it
    goes back to sent and its records to pending, so the next run sends the same root again
    (or, if it can no longer land, a new tree). How many records went back."""
    with transaction.atomic():
        changed = AnchorRoot.objects.filter(pk=tree.pk, status=AnchorRoot.Status.ANCHORED).update(
            status=AnchorRoot.Status.SENT, tx_hash="", block_number=None, anchored_at=None
        )
        if not changed:
            return 0
        return Record.objects.filter(anchor_root=tree, status=Record.Status.ANCHORED).update(
            status=Record.Status.PENDING,
            anchor_attempts=0,
            tx_hash="",
            block_number=None,
            anchored_at=None,
        )


def _exhausted(tree: AnchorRoot) -> bool:
    return Record.objects.filter(
        anchor_root=tree,
        status=Record.Status.PENDING,
        anchor_attempts__gte=settings.ANCHOR_MAX_ATTEMPTS,
    ).exists()


def _attempts_count(tree: AnchorRoot) -> None:
    Record.objects.filter(anchor_root=tree, status=Record.Status.PENDING).update(
        anchor_attempts=F("anchor_attempts") + 1
    )


def _attempts_return(trees: Sequence[AnchorRoot]) -> None:
    Record.objects.filter(
        anchor_root__in=list(trees), status=Record.Status.PENDING, anchor_attempts__gt=0
    ).update(anchor_attempts=F("anchor_attempts") - 1)


def record_path(record: Record) -> list[bytes]:
    """A record's audit path as stored: 32-byte hashes, from the leaf up."""
    return path_split(record.merkle_path)
