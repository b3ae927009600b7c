"""Deleting records (one, a selection, or by a robot's retention) and whole accounts.

A deletion is two steps, in this order:

1. the record becomes a tombstone, in one transaction: `deleted_at`, `deleted_by` and
   `deletion_reason` are set. From then on every view answers "deleted" (410), whatever
   storage still holds: nothing half-deleted is ever shown as live;
2. its ciphertext is removed from the envelope storage (local disk or S3) and the Redis
   cache, and `purged_at` is set.

A crash between the two leaves a tombstone whose ciphertext is still stored: never shown, and
removed by the next `records_purge` (queued after every deletion, and run first by each
`retention_apply`, the beat task). Removing what is gone already is no error, so every step
may run again, on any number of workers: rows are taken with select_for_update(skip_locked)
and a retention run holds a Redis lock.

The row stays with its digest, anchoring transaction and Merkle path: the digest is on chain
forever and the record's proof stays available, so anyone can still check that the deleted
data existed and what it hashed to. That is also why only anchored records are deleted (by
hand or by retention): a pending record's proof does not exist yet, and a failed one has none
until an operator anchors it again. Deleting an account is the exception: it deletes all.
"""

import logging
import uuid
from collections import Counter
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from datetime import datetime, timedelta

from botocore.exceptions import BotoCoreError, ClientError
from django.conf import settings
from django.contrib.auth.base_user import AbstractBaseUser
from django.db import transaction
from django.db.models import QuerySet
from django.utils import timezone

from accounts.events import account_event_record
from accounts.models import AccountEvent, Owner, Robot
from accounts.services.owners import owner_close, owner_password_confirm
from core.locks import LockUnavailable, lock_held
from core.outbox import enqueue
from core.redis_client import get_redis, redis_key
from sharing.cache import envelope_cache_evict
from sharing.errors import NoGrant, NotDeletableYet, NotRecordOwner, RecordNotFound
from sharing.models import Grant, Record
from sharing.selection import RecordSelection
from sharing.selectors.records import record_get_visible
from sharing.services.grants import EXPORTS_RECHECK_TASK, grant_revoke
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)

PURGE_TASK = "sharing.tasks.records_purge"
# Only one retention run at a time, whatever the number of workers and beats.
RETENTION_LOCK = "retention"


@dataclass(frozen=True)
class Deletion:
    """What a deletion of a selection did: records now deleted, and those left because they
    are not anchored yet (they may be deleted once they are)."""

    deleted: int
    not_anchored: int


def record_delete(*, owner: Owner, record_id: uuid.UUID | str, actor: AbstractBaseUser) -> Record:
    """Delete one of the owner's records. RecordNotFound if the owner cannot see it,
    NotRecordOwner if it is shared with the owner (a grantee deletes nothing),
    NotDeletableYet if it is not anchored. Deleting it again changes nothing."""
    record = record_get_visible(owner, record_id)
    if record is None:
        raise RecordNotFound("no such record, or not shared with you")
    if record.owner_id != owner.pk:
        raise NotRecordOwner("only the record's owner can delete it; you may only read it")
    if record.is_deleted:
        return record
    if record.status != Record.Status.ANCHORED:
        raise NotDeletableYet(
            "only anchored records are deleted (the deleted record keeps its proof on chain): "
            "try again once it is anchored"
        )
    records_delete(owner=owner, actor=actor, record_ids=[record.pk])
    record.refresh_from_db()
    return record


def records_delete(
    *,
    owner: Owner,
    actor: AbstractBaseUser,
    record_ids: Sequence[uuid.UUID] | None = None,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> Deletion:
    """Delete the owner's anchored records of a selection (each filter given narrows it;
    capture times [since, until)); records not anchored yet are left and counted."""
    selected = record_selection(
        owner, record_ids=record_ids, robot=robot, topic=topic, since=since, until=until
    )
    with transaction.atomic():
        deleted = _tombstone(
            selected.filter(status=Record.Status.ANCHORED),
            reason=Record.Deletion.OWNER,
            actor=actor,
        )
        not_anchored = selected.exclude(status=Record.Status.ANCHORED).count()
        if deleted:
            account_event_record(
                owner=owner,
                kind=AccountEvent.Kind.RECORDS_DELETED,
                actor=actor,
                detail={"records": deleted, "by": "the owner"},
            )
            transaction.on_commit(lambda: enqueue(PURGE_TASK))
    return Deletion(deleted=deleted, not_anchored=not_anchored)


def record_selection(
    owner: Owner,
    *,
    record_ids: Sequence[uuid.UUID] | None = None,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> QuerySet[Record]:
    """The owner's records of a selection that are not deleted yet."""
    records = Record.objects.filter(owner=owner).live()
    if record_ids is not None:
        records = records.filter(pk__in=list(record_ids))
    selection = RecordSelection.from_filters(robot=robot, topic=topic, since=since, until=until)
    return selection.apply(records)


def _tombstone(records: QuerySet[Record], *, reason: str, actor: AbstractBaseUser | None) -> int:
    """Step 1: mark the records deleted (those not deleted already); how many were. Exports
    that hold any of them are withdrawn after commit, their files removed with the data."""
    deleted = records.live().update(
        deleted_at=timezone.now(), deleted_by=actor, deletion_reason=reason
    )
    if deleted:
        transaction.on_commit(lambda: enqueue(EXPORTS_RECHECK_TASK))
    return deleted


# --- step 2: the ciphertext leaves storage and cache ---------------------------------------


def records_purge(*, batch: int | None = None, max_batches: int | None = None) -> int:
    """Remove the ciphertext of deleted records from storage and cache, in batches of
    `batch` rows (RETENTION_BATCH), at most `max_batches` (RETENTION_MAX_BATCHES) per call;
    how many were purged. A record whose removal fails (S3 unavailable) stays to purge and
    is tried again by the next call."""
    batch = batch or settings.RETENTION_BATCH
    max_batches = max_batches or settings.RETENTION_MAX_BATCHES
    purged = 0
    for _ in range(max_batches):
        done, tried = _purge_batch(batch)
        purged += done
        if tried < batch or done == 0:
            break
    return purged


def _purge_batch(batch: int) -> tuple[int, int]:
    """(purged, tried): one batch, its rows locked (other workers skip them) while their
    files are removed."""
    storage = envelope_storage()
    with transaction.atomic():
        rows = list(
            Record.objects.select_for_update(skip_locked=True)
            .filter(deleted_at__isnull=False, purged_at__isnull=True)
            .order_by("deleted_at", "pk")
            .values_list("pk", "storage_name")[:batch]
        )
        removed = []
        for record_id, name in rows:
            envelope_cache_evict(record_id)
            try:
                storage.delete(name)  # nothing there (a run cut short) is no error
            except (OSError, BotoCoreError, ClientError) as exc:
                logger.warning(
                    "deleted record %s: its ciphertext stays until the next run: %s", record_id, exc
                )
                continue
            # Again: a view that read the file before it went may have cached it meanwhile.
            envelope_cache_evict(record_id)
            removed.append(record_id)
        Record.objects.filter(pk__in=removed).update(purged_at=timezone.now())
    return len(removed), len(rows)


# --- retention ------------------------------------------------------------------------------


def retention_apply(*, now: datetime | None = None) -> dict[str, int]:
    """The beat task's run: finish purges left over, then delete the anchored records of
    each robot with a retention that were captured more than its retention days ago, in
    batches of RETENTION_BATCH, at most RETENTION_MAX_BATCHES per run (the next run goes on).

    Records not anchored yet are kept, and counted as `kept_not_anchored`: they are deleted
    by a later run once anchored (a failed one waits for an operator to anchor it again).
    One run at a time (a Redis lock): another run meanwhile returns at once, `skipped`.
    """
    try:
        with lock_held(
            redis_key("work", RETENTION_LOCK),
            client=get_redis(),
            timeout=settings.RETENTION_LOCK_TTL,
        ) as lock:
            if lock is None:
                return {"skipped": 1}
            return _retention_run(now or timezone.now())
    except LockUnavailable as exc:
        logger.warning("retention not run: Redis unavailable (%s)", exc)
        return {"skipped": 1}


def _retention_run(now: datetime) -> dict[str, int]:
    purged = records_purge()
    budget = settings.RETENTION_MAX_BATCHES
    deleted_per_owner: Counter[int] = Counter()
    kept = 0
    robots = Robot.objects.filter(
        retention_days__isnull=False, owner__deleted_at__isnull=True
    ).order_by("pk")
    for robot in robots:
        cutoff = now - timedelta(days=robot.retention_days)
        expired = Record.objects.filter(robot=robot).live().filter(captured_at__lt=cutoff)
        while budget > 0:
            with transaction.atomic():
                ids = list(
                    expired.filter(status=Record.Status.ANCHORED)
                    .select_for_update(skip_locked=True)
                    .order_by("captured_at", "pk")
                    .values_list("pk", flat=True)[: settings.RETENTION_BATCH]
                )
                if not ids:
                    break  # nothing of this robot's is due: no batch spent
                budget -= 1
                deleted = _tombstone(
                    Record.objects.filter(pk__in=ids), reason=Record.Deletion.RETENTION, actor=None
                )
            deleted_per_owner[robot.owner_id] += deleted
            purged += records_purge(max_batches=1)
            if len(ids) < settings.RETENTION_BATCH:
                break
        kept += expired.exclude(status=Record.Status.ANCHORED).count()
    for owner_id, count in deleted_per_owner.items():
        if count:
            account_event_record(
                owner=Owner.objects.get(pk=owner_id),
                kind=AccountEvent.Kind.RECORDS_DELETED,
                detail={"records": count, "by": "retention policy"},
            )
    deleted_total = sum(deleted_per_owner.values())
    if deleted_total or kept:
        logger.info(
            "retention: %d records deleted, %d purged, %d past retention kept (not anchored)",
            deleted_total,
            purged,
            kept,
        )
    return {"deleted": deleted_total, "purged": purged, "kept_not_anchored": kept}


# --- deleting an account --------------------------------------------------------------------


def account_delete(*, owner: Owner, password: str) -> Owner:
    """Delete the owner's account, confirmed with its password (WrongPassword otherwise):

    - every grant given and received is revoked (refused at once, authorityRevoke on chain);
    - every record is deleted, anchored or not (their ciphertext removed after commit);
    - sign-in, owner API tokens, robot tokens and pairing requests stop (accounts.owner_close).

    What stays: the tombstones, the username (so nobody can take it), and on chain forever the
    EOA, its key commitment, the digests and roots, and the grants' history.
    """
    owner_password_confirm(owner=owner, password=password)
    user = owner.user
    with transaction.atomic():
        live = Grant.objects.filter(status__in=Grant.LIVE).select_related("owner", "grantee")
        for grant in [*live.filter(owner=owner), *live.filter(grantee=owner)]:
            with suppress(NoGrant):  # revoked meanwhile
                grant_revoke(owner=grant.owner, grantee=grant.grantee)
        deleted = _tombstone(
            Record.objects.filter(owner=owner), reason=Record.Deletion.ACCOUNT, actor=user
        )
        owner_close(owner=owner, actor=user)
        transaction.on_commit(lambda: enqueue(PURGE_TASK))
    logger.info("account %s deleted: %d records to purge", owner.pk, deleted)
    owner.refresh_from_db()
    return owner
