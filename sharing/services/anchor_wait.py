"""What anchoring runs (one record per slot, or Merkle roots) share while they wait: receipts
awaited in steps that keep the owner's lock alive (core.locks.lock_renew), an owner's account
that cannot pay for gas, and records whose robot's key is not on chain yet.

Losing the owner's lock is safe, not fatal: a record id is written once on chain (records mode)
and a sender's roots are chained by prevRoot (root mode), so a duplicate send is refused and
settled from the chain. A run that lost it stops after the batch in hand."""

import logging
import time

from django.conf import settings
from django.db.models import Q, QuerySet
from redis.lock import Lock
from web3.types import TxReceipt

from accounts.models import ChainState, Owner
from alerts.services import anchoring_failed_alert
from chainworker.client import AuthROSChain
from chainworker.errors import TransactionTimeout
from chainworker.work import WAITING_FOR_GAS
from core.locks import lock_renew
from core.outbox import enqueue
from sharing.models import Record

logger = logging.getLogger("sharing.services.anchoring")

# Records signed by a robot key not confirmed on chain yet: anchored once it is (its
# confirmation queues the owner's run), since robotKeyOf must show the key added at or before
# their anchoring block (DESIGN.md "A record is genuine"). They use up no attempt meanwhile;
# unsigned records (a robot added by hand) never wait.
AWAITING_ROBOT_KEY = ~Q(signer="") & ~Q(robot__key_chain_state=ChainState.CONFIRMED)


def receipt_await(client: AuthROSChain, tx_hash: str, lock: Lock) -> TxReceipt:
    """Wait for the receipt in short steps, keeping the owner's anchoring lock alive."""
    deadline = time.monotonic() + client.receipt_timeout
    while True:
        step = min(settings.ANCHOR_LOCK_TTL / 3, max(deadline - time.monotonic(), 0.1))
        try:
            return client.wait_for_receipt(tx_hash, timeout=step)
        except TransactionTimeout:
            if time.monotonic() >= deadline:
                raise
            lock_renew(lock)


def gas_wait_start(owner_id: int, waiting: QuerySet) -> None:
    """The owner's account cannot pay for gas: an outage that waits, using up no attempt. The
    `waiting` records say why, and the operator is asked to top the account up."""
    waiting.update(failure_reason=WAITING_FOR_GAS)
    enqueue("accounts.tasks.owner_top_up", owner_id)


def gas_wait_end(owner_id: int) -> None:
    """The owner's account paid again: what waited for gas no longer does."""
    Record.objects.filter(
        owner_id=owner_id, status=Record.Status.PENDING, failure_reason=WAITING_FOR_GAS
    ).update(failure_reason="")


def records_fail_exhausted(owner: Owner, pending: QuerySet[Record]) -> int:
    """Fail the records among `pending` out of attempts (ANCHOR_MAX_ATTEMPTS), and tell their
    owner; how many."""
    exhausted = pending.filter(anchor_attempts__gte=settings.ANCHOR_MAX_ATTEMPTS)
    ids = list(exhausted.order_by("created_at", "seq").values_list("pk", flat=True))
    if not ids:
        return 0
    reason = f"not anchored after {settings.ANCHOR_MAX_ATTEMPTS} attempts"
    failed = Record.objects.filter(pk__in=ids, status=Record.Status.PENDING).update(
        status=Record.Status.FAILED, failure_reason=reason
    )
    if failed:
        anchoring_failed_alert(owner=owner, record_ids=ids, reason=reason)
    return failed
