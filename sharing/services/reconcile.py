"""Reconciliation: what the database says is on chain, compared with the chain and repaired.

A periodic job (`chain_reconcile`, Celery beat every RECONCILE_INTERVAL) first asks whether
the node is still the chain the portal deployed on (chainworker.services.chain_identity):
- the same chain: anchored records and Merkle roots (the recent ones every run, all of them
  in chunks of RECONCILE_CHUNK with a cursor in Redis), owners' registration and keys, their
  robots' keys (as each owner registered them: robotKeyOfOwner), and grants are read back
  from the chain. What the chain lacks goes back to pending and is sent
  again by the normal tasks; another digest or owner under a record id, or another size
  under a root, is a SecurityEvent; so is a robot key whose first owner on chain is another
  account (robot_key_dispute_record, with the owner's alert and an operator alert);
- a reset chain (new genesis or chain id, no contract code): on a development chain the
  contract is deployed again and everything re-created from the database (`chain_resync`);
  on a real network nothing is sent (chain_work_check) and the operator is told.
"""

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.db import transaction
from django.db.models import Exists, OuterRef, QuerySet
from django.utils import timezone

from accounts.models import ChainState, Owner
from accounts.services.registration import owners_chain_reset, owners_reconcile
from accounts.services.robot_keys import robot_keys_reconcile
from chainworker.client import AuthROSChain
from chainworker.services import (
    IDENTITY_RESET,
    IDENTITY_SAME,
    IDENTITY_UNDEPLOYED,
    chain_client,
    chain_identity,
    contract_redeploy_after_reset,
    reconcile_window,
)
from chainworker.work import ChainWorkNotReady
from core.locks import lock_held
from core.outbox import enqueue
from core.redis_client import get_redis, redis_key
from sharing.models import AnchorRoot, Grant, Record, SecurityEvent
from sharing.scope import scope_commitment
from sharing.services.anchoring import anchor_schedule, record_chain_mismatch
from sharing.services.roots import tree_lost

logger = logging.getLogger(__name__)

# One reconciliation or resync at a time. The lock is short and renewed while a run goes on:
# a worker killed in the middle frees it within RECONCILE_LOCK_TTL seconds.
RECONCILE_LOCK = "reconcile"
RECONCILE_LOCK_TTL = 30


def chain_reconcile() -> dict[str, object]:
    """The periodic job: repair what the chain lost, or handle a reset chain (see above).
    Returns what it found; a run while another is under way does nothing."""
    try:
        with _reconcile_lock(wait=0):
            identity = chain_identity()
            if identity.state == IDENTITY_UNDEPLOYED:
                return {"identity": identity.state}
            if identity.state == IDENTITY_RESET:
                if not identity.development:
                    logger.error(
                        "chain reset detected: %s. Nothing is sent until an operator acts: "
                        "check CHAIN_RPC_URL and the node, then `manage.py chain_resync`",
                        identity.reason,
                    )
                    return {"identity": identity.state, "reason": identity.reason}
                logger.warning(
                    "chain reset detected on a development chain: %s; deploying again and "
                    "re-creating everything from the database",
                    identity.reason,
                )
                return {"identity": identity.state, **_resync()}
            counts: dict[str, object] = {"identity": identity.state}
            owners = _owners_window()
            counts.update(owners_reconcile(owners=owners))
            counts.update(robot_keys_reconcile(owners=owners))
            counts.update(records_reconcile())
            counts.update(roots_reconcile())
            counts.update(grants_reconcile())
            return counts
    except ChainWorkNotReady:
        return {"skipped": "another reconciliation is under way"}


def chain_resync() -> dict[str, object]:
    """Re-create everything on chain from the database, on demand (`manage.py chain_resync`):
    on a reset chain the contract is deployed first; then every owner goes back to pending
    registration, every active grant to pending, every anchored record to pending, and the
    normal tasks send them again (idempotent: what is on chain already is skipped)."""
    with _reconcile_lock(wait=30):
        return _resync()


@contextmanager
def _reconcile_lock(*, wait: float) -> Iterator[None]:
    """Hold the reconciliation lock, renewed every RECONCILE_LOCK_TTL / 3 seconds by a thread
    while the run goes on; ChainWorkNotReady if another run holds it after `wait` seconds."""
    with lock_held(
        redis_key("work", RECONCILE_LOCK),
        client=get_redis(),
        timeout=RECONCILE_LOCK_TTL,
        wait=wait,
        renew_every=RECONCILE_LOCK_TTL / 3,
    ) as lock:
        if lock is None:
            raise ChainWorkNotReady("a reconciliation is under way in another worker")
        yield


def _resync() -> dict[str, object]:
    counts: dict[str, object] = {}
    if chain_identity().state != IDENTITY_SAME:
        outcome = contract_redeploy_after_reset()
        counts["deployed"] = outcome.deployment.address
        logger.warning(
            "AuthROS deployed at %s (%s); re-creating everything from the database",
            outcome.deployment.address,
            outcome.reason,
        )
    with transaction.atomic():
        # Owners first: their registration, queued on commit, queues their records' anchoring.
        counts["owners"] = len(owners_chain_reset())
        grants = list(Grant.objects.filter(status__in=Grant.LIVE).order_by("pk"))
        Grant.objects.filter(pk__in=[g.pk for g in grants], status=Grant.Status.ACTIVE).update(
            status=Grant.Status.PENDING, grant_tx="", grant_block=None, updated_at=timezone.now()
        )
        for grant in grants:
            transaction.on_commit(lambda g=grant.pk: enqueue("sharing.tasks.grant_sync", g))
        counts["grants"] = len(grants)
        # Trees go back to sent: each is sent again as it was, after the same previous root.
        counts["roots"] = AnchorRoot.objects.filter(status=AnchorRoot.Status.ANCHORED).update(
            status=AnchorRoot.Status.SENT, tx_hash="", block_number=None, anchored_at=None
        )
        counts["records"] = Record.objects.filter(status=Record.Status.ANCHORED).update(
            status=Record.Status.PENDING,
            anchor_attempts=0,
            tx_hash="",
            block_number=None,
            anchored_at=None,
        )
    logger.warning("chain resync queued: %s", counts)
    return counts


def records_reconcile() -> dict[str, int]:
    """Read back anchored records from the chain: the ones anchored in the last
    ANCHOR_STALE_AFTER * 10 seconds (at most RECONCILE_CHUNK) and the next RECONCILE_CHUNK of
    all of them. One missing on chain goes back to pending and anchoring is queued; another
    digest or owner under its id fails it with a SecurityEvent."""
    anchored = Record.objects.filter(
        status=Record.Status.ANCHORED, anchor_root__isnull=True
    ).select_related("owner")  # records under a root: roots_reconcile
    records = _recent_and_window(anchored, name="records")
    client = chain_client()
    lost: list[Record] = []
    mismatches = 0
    for record in records.values():
        on_chain = client.data_query(record.id, owner=record.owner.eoa_address)
        if on_chain is None:
            lost.append(record)
        elif on_chain.digest.hex() != record.digest or (
            on_chain.owner.lower() != record.owner.eoa_address.lower()
        ):
            record_chain_mismatch(
                record=record, chain_digest=on_chain.digest.hex(), chain_owner=on_chain.owner
            )
            mismatches += 1
    requeued = 0
    for owner_id in sorted({record.owner_id for record in lost}):
        ids = [record.pk for record in lost if record.owner_id == owner_id]
        # Only records still as we read them: one anchored again meanwhile is left alone.
        requeued += Record.objects.filter(pk__in=ids, status=Record.Status.ANCHORED).update(
            status=Record.Status.PENDING,
            anchor_attempts=0,
            tx_hash="",
            block_number=None,
            anchored_at=None,
        )
        # A chain that lost blocks lost the owner's transactions too: count from the node.
        client.resync_nonce(next(r.owner.eoa_address for r in lost if r.owner_id == owner_id))
        anchor_schedule(owner_id=owner_id)
    if lost:
        logger.warning("the chain lost %d anchored record(s): anchoring them again", len(lost))
    return {"records_checked": len(records), "records_lost": requeued, "digests": mismatches}


def roots_reconcile() -> dict[str, int]:
    """Read back anchored Merkle roots, as records_reconcile reads records: a root its sender
    has not anchored on this chain goes back to sent, with its records, and anchoring is
    queued; one anchored with another size is also a SecurityEvent."""
    anchored = AnchorRoot.objects.filter(status=AnchorRoot.Status.ANCHORED).select_related("owner")
    trees = _recent_and_window(anchored, name="roots")
    client = chain_client()
    lost: list[AnchorRoot] = []
    for tree in trees.values():
        on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
        if on_chain is not None and on_chain.size == tree.size:
            continue
        if on_chain is not None:
            SecurityEvent.objects.create(
                kind=SecurityEvent.Kind.CHAIN_DIGEST_MISMATCH,
                owner=tree.owner,
                detail={"root": tree.root, "size": tree.size, "chain_size": on_chain.size},
            )
            logger.error(
                "root %s: the chain holds size %s, we hold %s", tree.root, on_chain.size, tree.size
            )
        lost.append(tree)
    requeued = 0
    for owner_id in sorted({tree.owner_id for tree in lost}):
        mine = [tree for tree in lost if tree.owner_id == owner_id]
        requeued += sum(tree_lost(tree) for tree in mine)
        client.resync_nonce(mine[0].sender)
        anchor_schedule(owner_id=owner_id)
    if lost:
        logger.warning(
            "the chain lost %d root(s) of %d record(s): anchoring them again", len(lost), requeued
        )
    return {"roots_checked": len(trees), "roots_lost": len(lost)}


def _recent_and_window(anchored: QuerySet, *, name: str) -> dict[Any, Any]:
    """The rows of `anchored` (by primary key) a run reads back: those anchored in the last
    ANCHOR_STALE_AFTER * 10 seconds (at most RECONCILE_CHUNK) and the next RECONCILE_CHUNK of
    all of them (a cursor per `name`)."""
    since = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER * 10)
    recent = list(
        anchored.filter(anchored_at__gte=since).order_by("-anchored_at")[: settings.RECONCILE_CHUNK]
    )
    window = reconcile_window(name=name, queryset=anchored, size=settings.RECONCILE_CHUNK)
    return {row.pk: row for row in [*recent, *window]}


def _grant_holds(client: AuthROSChain, grant: Grant) -> bool:
    """Whether the chain gives the grantee access: for an active grant, with the portal's
    terms (scope commitment and expiry; an expired one counts as holding: it ran out, it was
    not lost); for a revoked one, any access at all."""
    owner, grantee = grant.owner.eoa_address, grant.grantee.eoa_address
    on_chain = client.grant_of(owner, grantee)
    if on_chain is None:  # a contract from before scoped grants
        return client.has_access(owner, grantee)
    if grant.status != Grant.Status.ACTIVE:
        return on_chain.live
    return (on_chain.live or grant.is_expired) and (on_chain.scope, on_chain.expiry) == (
        scope_commitment(grant.scope),
        grant.expiry,
    )


def grants_reconcile() -> dict[str, int]:
    """Read back grants from the chain (RECONCILE_CHUNK at a time): an active grant without
    access on chain goes back to pending, a revoked one (the pair's newest, with no live grant
    after it) with access goes back to revoking; grant_sync is queued for each."""
    confirmed = {
        "owner__chain_state": ChainState.CONFIRMED,
        "grantee__chain_state": ChainState.CONFIRMED,
    }
    later = Grant.objects.filter(
        owner=OuterRef("owner"), grantee=OuterRef("grantee"), created_at__gt=OuterRef("created_at")
    )
    candidates = Grant.objects.filter(
        status__in=[Grant.Status.ACTIVE, Grant.Status.REVOKED], **confirmed
    ).exclude(Exists(later))
    grants = reconcile_window(
        name="grants",
        queryset=candidates.select_related("owner", "grantee"),
        size=settings.RECONCILE_CHUNK,
    )
    client = chain_client()
    regranted = revoked_again = 0
    for grant in grants:
        access = _grant_holds(client, grant)
        if grant.status == Grant.Status.ACTIVE and not access:
            target, count_as = Grant.Status.PENDING, "granted"
        elif grant.status == Grant.Status.REVOKED and access:
            target, count_as = Grant.Status.REVOKING, "revoked"
        else:
            continue
        changed = Grant.objects.filter(pk=grant.pk, status=grant.status).update(
            status=target, updated_at=timezone.now()
        )
        if not changed:
            continue
        if count_as == "granted":
            regranted += 1
        else:
            revoked_again += 1
        logger.warning("grant %s differs on chain (%s): sending it again", grant.pk, grant.status)
        enqueue("sharing.tasks.grant_sync", grant.pk)
    return {"grants_checked": len(grants), "grants_lost": regranted, "revokes_lost": revoked_again}


def _owners_window() -> list[Owner]:
    return reconcile_window(
        name="owners",
        queryset=Owner.objects.filter(chain_state=ChainState.CONFIRMED),
        size=settings.RECONCILE_CHUNK,
    )
