"""The integrity check at view time, and reading a record's content through it.

The worker runs `record_verify`: access on chain, one fetch of the stored envelope (Redis
cache, else durable storage), one SM3 hash, compared with the digest on chain; it leaves a
Verdict and hands back the bytes it checked. The web process (`record_open`) decrypts those
very bytes, and only when the verdict is `verified`; a refusal carries its record and verdict.
"""

import base64
import logging
import uuid
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from typing import Any

from django.conf import settings
from django.utils import timezone
from redis.exceptions import RedisError

from accounts.models import Owner
from accounts.selectors import owner_key_bytes, owner_key_current
from chainworker.chain import AuthROSChain
from chainworker.services import chain_client
from core.outbox import dispatch
from sharing.cache import envelope_cache_evict, envelope_fetch
from sharing.errors import (
    AccessDenied,
    IntegrityCheckFailed,
    NotAnchoredYet,
    RecordNotFound,
    SharingError,
    VerificationUnavailable,
)
from sharing.models import Grant, Record, SecurityEvent, Verdict
from smcrypto import envelope, sm3

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

VERIFY_TASK = "sharing.tasks.record_verify"


# --- the check, in the worker ------------------------------------------------------------------


@dataclass(frozen=True)
class Verification:
    verdict: Verdict
    envelope: bytes | None  # the bytes that were checked; only when verified


def record_verify(
    *, record_id: uuid.UUID | str, viewer_id: int, checked_by_id: int | None = None
) -> Verification:
    """Check access on chain and the stored envelope's SM3 digest against the chain.

    Every check leaves a Verdict: the audit trail of who viewed what, when, at which block.
    `checked_by_id` names the operator running the check with the viewer's rights (the admin
    console's re-verify), so that it is not recorded as the viewer's own view.
    """
    record = Record.objects.select_related("owner").get(pk=record_id)
    viewer = Owner.objects.get(pk=viewer_id)
    client = chain_client()
    block = client.latest_block()

    def verdict(outcome: str, **fields: object) -> Verdict:
        return Verdict.objects.create(
            record=record,
            viewer=viewer,
            checked_by_id=checked_by_id,
            outcome=outcome,
            block_number=block,
            **fields,
        )

    if not _may_view(record, viewer, client):
        return Verification(verdict(Verdict.Outcome.NO_ACCESS), None)
    data, source = envelope_fetch(record)
    computed = sm3.sm3_hex(data)
    on_chain = client.data_query(record.id)
    if on_chain is None:
        return Verification(
            verdict(Verdict.Outcome.NOT_ANCHORED_YET, computed_digest=computed, source=source),
            None,
        )
    chain_digest = on_chain.digest.hex()
    if chain_digest != computed or on_chain.owner.lower() != record.owner.eoa_address.lower():
        _record_tampered(record, viewer, source=source, computed=computed, chain=chain_digest)
        return Verification(
            verdict(
                Verdict.Outcome.TAMPERED,
                computed_digest=computed,
                chain_digest=chain_digest,
                source=source,
            ),
            None,
        )
    return Verification(
        verdict(
            Verdict.Outcome.VERIFIED,
            computed_digest=computed,
            chain_digest=chain_digest,
            source=source,
        ),
        data,
    )


def verification_answer(verification: Verification) -> dict[str, Any]:
    """What the worker hands back to the view (JSON through the result backend)."""
    data = verification.envelope
    return {
        "verdict_id": verification.verdict.pk,
        "outcome": verification.verdict.outcome,
        "envelope": base64.b64encode(data).decode("ascii") if data is not None else None,
    }


def _may_view(record: Record, viewer: Owner, client: AuthROSChain) -> bool:
    """The owner, or a grantee whose grant is live in the portal and on chain."""
    if viewer.pk == record.owner_id:
        return True
    live = Grant.objects.filter(
        owner_id=record.owner_id, grantee=viewer, status=Grant.Status.ACTIVE
    ).exists()
    if not live:
        return False
    return client.has_access(record.owner.eoa_address, viewer.eoa_address)


def _record_tampered(
    record: Record, viewer: Owner, *, source: str, computed: str, chain: str
) -> None:
    Record.objects.filter(pk=record.pk).update(tampered_at=timezone.now())
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.TAMPERED_ON_VIEW,
        record=record,
        owner=record.owner,
        detail={"viewer": viewer.username, "source": source, "computed": computed, "chain": chain},
    )
    security_log.error(
        "record %s failed its integrity check (%s copy): computed %s, chain %s",
        record.pk,
        source,
        computed,
        chain,
    )
    # The next view reads durable storage again instead of the bad cached copy.
    envelope_cache_evict(record.pk)


# --- reading content, in the web process -------------------------------------------------------


@dataclass(frozen=True)
class OpenedRecord:
    """A record that passed its integrity check, decrypted for one viewer."""

    record: Record
    verdict: Verdict
    header: dict
    plaintext: bytes
    envelope: bytes  # the bytes the worker checked against the chain


def record_open(*, record_id: uuid.UUID | str, viewer: Owner) -> OpenedRecord:
    """Have the worker check the record, then decrypt what it checked.

    Raises RecordNotFound, VerificationUnavailable, or (with the record and the verdict
    attached) AccessDenied, IntegrityCheckFailed or NotAnchoredYet.
    """
    try:
        record = Record.objects.select_related("owner__user").get(pk=uuid.UUID(str(record_id)))
    except (ValueError, Record.DoesNotExist):
        raise RecordNotFound("no such record") from None
    return _opened(record, viewer, _send_verify(record, viewer))


def record_open_many(
    *, records: Sequence[Record], viewer: Owner
) -> list[OpenedRecord | SharingError]:
    """record_open for several records at once: every check is queued before any answer is
    awaited, so they run side by side on the verify workers. One result per record, in
    order: the opened record, or the SharingError record_open would have raised."""
    sent = [(record, _send_verify(record, viewer)) for record in records]
    results: list[OpenedRecord | SharingError] = []
    for record, pending in sent:
        try:
            results.append(_opened(record, viewer, pending))
        except SharingError as exc:
            results.append(exc)
    return results


def record_reseal_for(*, opened: OpenedRecord, viewer: Owner) -> bytes:
    """The record's content sealed under the viewer's own current key (same header)."""
    return envelope.seal(
        owner_key_bytes(owner_key_current(viewer)), opened.header, opened.plaintext
    )


def _send_verify(record: Record, viewer: Owner) -> Any:
    """Queue the worker's integrity check; an exception instead if it cannot be queued."""
    try:
        return dispatch(VERIFY_TASK, str(record.pk), viewer.pk)
    except Exception as exc:  # the broker is down
        return exc


def _opened(record: Record, viewer: Owner, pending: Any) -> OpenedRecord:
    verdict, data = _worker_answer(record, viewer, pending)
    if verdict.outcome == Verdict.Outcome.NO_ACCESS:
        raise AccessDenied("you have no live grant to this record", record=record, verdict=verdict)
    if verdict.outcome == Verdict.Outcome.TAMPERED:
        raise IntegrityCheckFailed(
            "the stored data differs from the digest on chain", record=record, verdict=verdict
        )
    if verdict.outcome == Verdict.Outcome.NOT_ANCHORED_YET or data is None:
        raise NotAnchoredYet(
            "the record is not anchored on chain yet", record=record, verdict=verdict
        )
    key = record.owner.keys.get(key_id=record.key_id)
    header, plaintext = envelope.open(owner_key_bytes(key), data)
    return OpenedRecord(record, verdict, header, plaintext, data)


def _worker_answer(record: Record, viewer: Owner, pending: Any) -> tuple[Verdict, bytes | None]:
    """The verdict the worker left and the bytes it checked (when verified)."""
    try:
        if isinstance(pending, Exception):
            raise pending
        try:
            answer = pending.get(timeout=settings.VERIFY_TIMEOUT, disable_sync_subtasks=False)
        finally:
            # The answer may hold a whole envelope: it is not kept in Redis once read (a
            # failure to drop it only leaves it to expire with CELERY_RESULT_EXPIRES).
            with suppress(RedisError, OSError):
                pending.forget()
    except Exception as exc:  # timeout, broker down, or the worker's own failure
        logger.warning("verification of %s for %s failed: %s", record.pk, viewer, exc)
        raise VerificationUnavailable(
            "the integrity check could not run now; nothing is shown: try again shortly"
        ) from exc
    verdict = Verdict.objects.get(pk=answer["verdict_id"])
    encoded = answer.get("envelope")
    return verdict, base64.b64decode(encoded) if encoded is not None else None
