"""Reading records' content in the web process, only through the worker's check: `records_open`
(a page of a gallery, a plot, a robot's page) and `record_open` for one record (a record page,
a content answer), the single record being N = 1 of the same path.

The web reads each record row once, opens the read's Access (one per record owner), sends the
records in batches of VERIFY_BATCH all at once (so that a plot of 18,000 records is checked by
every verify worker side by side), unwraps each key once while the workers check, and decrypts
once the very bytes the worker checked against the chain, only where its verdict is `verified`;
a refusal carries its record and verdict. The plaintext never leaves the web process: the
worker hands back the envelope it checked, never what it decrypted to check a signature.
`record_reseal_for` seals the content for the viewer with the keys the read unwrapped.

A series (`records_rows_open`) is the exception that needs no content: its slices go to the
series task, which checks them the same way and hands back only the plotted numbers of the
verified ones, sealed under a key of this read (verification/answers.py), not envelopes.

A read is charged its records before anything is sent (verification/budget.py); it stops
waiting at the first batch not answered in VERIFY_TIMEOUT, or once its client closed the
connection, and then its batches no worker has started are not run.
"""

import base64
import logging
import time
import uuid
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from celery.exceptions import TimeoutError as CeleryTimeoutError
from django.conf import settings
from redis.exceptions import RedisError

from accounts.errors import IdentityMismatch
from accounts.models import Owner, OwnerToken
from accounts.selectors import owner_key_current
from core.client import client_gone
from core.outbox import dispatch
from sharing.errors import (
    NOT_VISIBLE,
    AccessDenied,
    IntegrityCheckFailed,
    NotAnchoredYet,
    RecordDeleted,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.models import Access, Credential, Record, Verdict
from sharing.selectors.records import record_deletion_text, record_to_open
from sharing.verification.access import (
    OwnerRead,
    accesses_open,
    accesses_open_for,
    accesses_withdraw,
    credential_check,
    reads_new_to_lines,
)
from sharing.verification.answers import answer_key_make, answer_open
from sharing.verification.budget import CheckRun, check_run
from sharing.verification.check import ANSWERED_FIELDS
from sharing.verification.direct import direct_check_send
from sharing.verification.keys import RecordKeys
from smcrypto import envelope

logger = logging.getLogger(__name__)

VERIFY_TASK = "sharing.tasks.records_verify"
# Records per task: a bigger read is sent as several tasks at once, which the verify workers
# take side by side; each answer holds its batch's envelopes (about 1 KB each for odometry).
VERIFY_BATCH = 1000
# How often a read waiting for its checks looks whether its client is still there.
CLIENT_POLL_SECONDS = 1.0


class ClientGone(Exception):
    """The client of the request a read waits for closed its connection."""


@dataclass(frozen=True)
class OpenedRecord:
    """A record that passed its integrity check, decrypted for one viewer."""

    record: Record
    verdict: Verdict
    header: dict
    plaintext: bytes
    envelope: bytes  # the bytes the worker checked against the chain
    # The keys the read unwrapped, so that re-sealing for the viewer unwraps none again.
    keys: RecordKeys = field(default_factory=RecordKeys, repr=False, compare=False)


def record_open(
    *,
    record_id: uuid.UUID | str,
    viewer: Owner,
    credential: str = Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> OpenedRecord:
    """records_open of one record (a record page, a content answer), by its id.

    Raises RecordNotFound, VerificationUnavailable, or (with the record and the verdict
    attached) AccessDenied, RecordDeleted, IntegrityCheckFailed or NotAnchoredYet.
    """
    try:
        record = record_to_open(uuid.UUID(str(record_id)))
    except ValueError:
        record = None
    if record is None:
        raise RecordNotFound(NOT_VISIBLE)
    (opened,) = records_open(
        records=[record],
        viewer=viewer,
        kind=Access.Kind.VIEW,
        credential=credential,
        token=token,
    )
    if isinstance(opened, SharingError):
        raise opened
    return opened


def records_open(
    *,
    records: Sequence[Record],
    viewer: Owner,
    kind: str,
    credential: str,
    token: OwnerToken | None = None,
) -> list[OpenedRecord | SharingError]:
    """Have the worker check the records, then decrypt what it checked: one Access of `kind`
    (per record owner) in the access log, opened first so that every batch's verdicts point
    to it, the records sent in batches of VERIFY_BATCH all at once, the keys unwrapped while
    the worker checks. A read refused whole is coalesced by the worker as a refused view is
    (its line removed); a read no worker could answer leaves no line. One result per record,
    in order: the opened record, or the SharingError that refuses it (VerificationUnavailable
    for each of a batch the worker could not answer). `credential` (and `token`, an owner API
    token's) is the viewer's credential that asked. IdentityMismatch is raised as the worker
    raised it; CheckBudgetExceeded before anything is checked or logged, when the records are
    more than the viewer's budget of checks holds now (sharing/verification/budget.py)."""
    token_id = token.pk if token is not None else None
    credential_check(credential, token_id)
    if not records:
        return []
    with check_run(caller_id=viewer.pk, records=len(records)) as run:
        return _records_checked(records, viewer, kind, credential, token_id, run)


def _records_checked(
    records: Sequence[Record],
    viewer: Owner,
    kind: str,
    credential: str,
    token_id: int | None,
    run: CheckRun,
) -> list[OpenedRecord | SharingError]:
    """records_open's work, its records charged to the viewer's budget as `run`: the batches
    sent at once, then waited for in order, each up to VERIFY_TIMEOUT; once one is not
    answered the read stops waiting, and its batches no worker has started are not run."""
    accesses = accesses_open(
        kind=kind, viewer_id=viewer.pk, records=records, credential=credential, token_id=token_id
    )
    sent_accesses = {str(owner_id): access_id for owner_id, access_id in accesses.items()}
    batches = [records[at : at + VERIFY_BATCH] for at in range(0, len(records), VERIFY_BATCH)]
    # One record (a record page, a content answer) is asked of a verify worker directly,
    # without Celery's round trip (sharing/verification/direct.py); pages and plots go
    # through the queue, where the verify workers take their batches side by side.
    send = _send_direct if len(records) == 1 and settings.VERIFY_DIRECT else _send
    pending = [
        send(
            VERIFY_TASK,
            [str(record.pk) for record in batch],
            viewer.pk,
            credential,
            token_id,
            sent_accesses,
            kind,
            run.id,
        )
        for batch in batches
    ]
    run.refund(
        sum(len(b) for b, p in zip(batches, pending, strict=True) if isinstance(p, Exception))
    )
    keys = RecordKeys()
    keys.warm(records)  # while the worker checks
    results: list[OpenedRecord | SharingError] = []
    answered = False
    stopped: VerificationUnavailable | None = None
    try:
        for batch, sent in zip(batches, pending, strict=True):
            if stopped is not None:
                results += [VerificationUnavailable(str(stopped)) for _ in batch]
                continue
            run.waiting()  # the batches not started yet stay wanted while this one is awaited
            try:
                answers = _await_answer(sent, f"{len(batch)} records", viewer)
            except VerificationUnavailable as exc:
                results += [VerificationUnavailable(str(exc)) for _ in batch]
                if not isinstance(sent, Exception):
                    stopped = exc  # not answered: the read waits for no other batch
                continue
            results += _batch_opened(batch, answers, viewer, keys)
            answered = True
    finally:
        if not answered:  # no check ran: a line without verdicts is no access
            accesses_withdraw(accesses, ())
    return results


def _batch_opened(
    batch: Sequence[Record], answers: list[dict[str, Any]], viewer: Owner, keys: RecordKeys
) -> list[OpenedRecord | SharingError]:
    """Each record of a batch the worker answered: opened, or why not."""
    by_record = {answer["record_id"]: answer for answer in answers}
    results: list[OpenedRecord | SharingError] = []
    for record in batch:
        answer = by_record.get(str(record.pk))
        try:
            if answer is None:  # gone meanwhile, or answered as a refused read before it
                raise RecordNotFound(NOT_VISIBLE)
            verdict = _verdict_of(answer, record, viewer)
            results.append(_decrypted(record, verdict, _envelope_of(answer), keys))
        except SharingError as exc:
            results.append(exc)
    return results


def record_reseal_for(*, opened: OpenedRecord, viewer: Owner) -> bytes:
    """The record's content sealed under the viewer's own current key (same header); a key
    the read unwrapped already (the owner's own record) is not unwrapped again."""
    key = opened.keys.of_owner_key(owner_key_current(viewer))
    return envelope.seal(key, opened.header, opened.plaintext)


def _send(task_name: str, *args: Any) -> Any:
    """Queue the worker's integrity check; an exception instead if it cannot be queued."""
    try:
        return dispatch(task_name, *args)
    except Exception as exc:  # the broker is down
        return exc


def _send_direct(task_name: str, *args: Any) -> Any:
    """The check asked of a verify worker through Redis, or sent as the task when no worker
    serves there (`_send`)."""
    try:
        direct = direct_check_send(*args)
    except (RedisError, OSError) as exc:
        return exc
    return direct if direct is not None else _send(task_name, *args)


def _verdict_of(answer: dict[str, Any], record: Record, viewer: Owner) -> Verdict:
    """The verdict the worker wrote, as it answered it (not read back)."""
    return Verdict(
        pk=answer["verdict_id"],
        record=record,
        created_at=datetime.fromisoformat(answer["created_at"]),
        **{name: answer[name] for name in ANSWERED_FIELDS},
    )


def _decrypted(
    record: Record, verdict: Verdict, data: bytes | None, keys: RecordKeys
) -> OpenedRecord:
    """The record decrypted from the bytes the worker checked, if its verdict allows."""
    if verdict.outcome == Verdict.Outcome.NO_ACCESS:
        raise AccessDenied(NOT_VISIBLE, record=record, verdict=verdict)
    if verdict.outcome == Verdict.Outcome.DELETED:
        record.refresh_from_db()
        raise RecordDeleted(record_deletion_text(record), record=record, verdict=verdict)
    if verdict.outcome == Verdict.Outcome.TAMPERED:
        raise IntegrityCheckFailed(
            "the stored data differs from the digest on chain", record=record, verdict=verdict
        )
    if verdict.outcome == Verdict.Outcome.SIGNATURE_REFUSED:
        raise IntegrityCheckFailed(
            "the record is anchored, but its robot signature does not hold: it is not shown "
            "as genuine",
            record=record,
            verdict=verdict,
        )
    if verdict.outcome == Verdict.Outcome.NOT_ANCHORED_YET or data is None:
        raise NotAnchoredYet(
            "the record is not anchored on chain yet", record=record, verdict=verdict
        )
    header, plaintext = envelope.open(keys.of(record), data)
    return OpenedRecord(record, verdict, header, plaintext, data, keys)


def _await_answer(pending: Any, what: str, viewer: Owner) -> Any:
    """The worker's answer (verification_answer, or a list of them); VerificationUnavailable
    if it cannot be had."""
    try:
        if isinstance(pending, Exception):
            raise pending
        try:
            answer = _answer_while_wanted(pending)
        finally:
            # The answer may hold a whole envelope: it is not kept in Redis once read (a
            # failure to drop it only leaves it to expire with CELERY_RESULT_EXPIRES).
            with suppress(RedisError, OSError):
                pending.forget()
    except IdentityMismatch:
        raise  # the worker's refusal: the owner's commitment on chain is not the portal's key
    except Exception as exc:  # timeout, client gone, broker down, or the worker's own failure
        logger.warning("verification of %s for %s failed: %s", what, viewer, exc)
        raise VerificationUnavailable(
            "the integrity check could not run now; nothing is shown: try again shortly"
        ) from exc
    return answer


def _answer_while_wanted(pending: Any) -> Any:
    """The task's answer, waited for up to VERIFY_TIMEOUT, in slices of CLIENT_POLL_SECONDS
    between which the client's connection is looked at: ClientGone once it closed it."""
    deadline = time.monotonic() + settings.VERIFY_TIMEOUT
    while True:
        left = deadline - time.monotonic()
        try:
            return pending.get(
                timeout=max(0.0, min(left, CLIENT_POLL_SECONDS)), disable_sync_subtasks=False
            )
        except CeleryTimeoutError:
            if left <= CLIENT_POLL_SECONDS:
                raise
            if client_gone():
                raise ClientGone("the client closed its connection") from None


def _envelope_of(answer: dict[str, Any]) -> bytes | None:
    """The bytes the worker checked, when it found them verified."""
    encoded = answer.get("envelope")
    return base64.b64decode(encoded) if encoded is not None else None


SERIES_TASK = "sharing.tasks.series_verify"
# Records per series task: a slice's answer is its rows only (a few numbers a record), so a
# slice is bigger than a page's batch; the slices are sent at once for the workers side by side.
SERIES_BATCH = 2000


@dataclass(frozen=True)
class CheckedRows:
    """What the workers answered for a series: how many of its records they verified, and the
    verified ones' rows [t, v1, v2...] in the order asked."""

    verified: int
    rows: list[list[float | None]]


def records_rows_open(
    *,
    record_ids: Sequence[str],
    reads: Sequence[OwnerRead],
    viewer: Owner,
    fields: Sequence[str],
    credential: str,
    token: OwnerToken | None = None,
    refresh: bool = False,
) -> CheckedRows:
    """A series' records checked by the workers (sharing.tasks.series_verify), every one at
    every read: the plot's Access opened first (one per record owner, from `reads`), the
    records sent in slices of SERIES_BATCH all at once, each slice's rows handed back sealed
    under this read's answer key (verification/answers.py) and opened here. A record refused
    or gone is not among the rows; the verified count says how many are. VerificationUnavailable
    if a slice could not be answered (the read then stops waiting: slices no worker started are
    not run; verdicts written are kept); a read no worker answered leaves no line. A `refresh`
    (a plot's newer records) adds to the viewer's recent line of the same plot
    (accesses_open_for). CheckBudgetExceeded before anything is checked or logged, when the
    records are more than the viewer's budget of checks holds now (verification/budget.py)."""
    token_id = token.pk if token is not None else None
    credential_check(credential, token_id)
    if not record_ids:
        return CheckedRows(0, [])
    with check_run(caller_id=viewer.pk, records=len(record_ids)) as run:
        return _rows_checked(record_ids, reads, viewer, fields, credential, token_id, refresh, run)


def _rows_checked(
    record_ids: Sequence[str],
    reads: Sequence[OwnerRead],
    viewer: Owner,
    fields: Sequence[str],
    credential: str,
    token_id: int | None,
    refresh: bool,
    run: CheckRun,
) -> CheckedRows:
    """records_rows_open's work, its records charged to the viewer's budget as `run`: the
    slices sent at once, then waited for in order; once one is not answered the read stops
    waiting, and its slices no worker has started are not run."""
    if refresh:
        reads = reads_new_to_lines(
            viewer_id=viewer.pk,
            reads=reads,
            record_ids=record_ids,
            credential=credential,
            token_id=token_id,
        )
    accesses = accesses_open_for(
        kind=Access.Kind.PLOT,
        viewer_id=viewer.pk,
        reads=reads,
        credential=credential,
        token_id=token_id,
        refresh=refresh,
    )
    sent_accesses = {str(owner_id): access_id for owner_id, access_id in accesses.items()}
    key = answer_key_make()
    slices = [
        list(record_ids[at : at + SERIES_BATCH]) for at in range(0, len(record_ids), SERIES_BATCH)
    ]
    pending = [
        _send(
            SERIES_TASK,
            ids,
            viewer.pk,
            credential,
            token_id,
            sent_accesses,
            list(fields),
            key.read_id,
            key.wrapped,
            part,
            run.id,
        )
        for part, ids in enumerate(slices)
    ]
    run.refund(
        sum(len(i) for i, p in zip(slices, pending, strict=True) if isinstance(p, Exception))
    )
    verified, rows, unavailable = 0, [], None
    answered = False
    try:
        for part, (ids, sent) in enumerate(zip(slices, pending, strict=True)):
            run.waiting()  # the slices not started yet stay wanted while this one is awaited
            try:
                answer = _await_answer(sent, f"{len(ids)} records of a series", viewer)
            except VerificationUnavailable as exc:
                unavailable = exc
                if isinstance(sent, Exception):
                    continue
                break  # not answered: the read waits for no other slice
            answered = True
            verified += answer["verified"]
            rows += answer_open(key=key, part=part, sealed=answer["rows"])
    finally:
        if not answered:  # no check ran: a line without verdicts is no access
            accesses_withdraw(accesses, reads, refresh=refresh)
    if unavailable is not None:
        raise unavailable
    return CheckedRows(verified, rows)
