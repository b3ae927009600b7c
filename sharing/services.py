"""Actions on records and grants, and the integrity check at view time.

Uploads are committed (row and durable envelope) before they are acknowledged; anchoring is
queued on commit and retried by the sweep. Grants and revocations take effect in the portal
at once and are mirrored on chain by the worker.
"""

import logging
import uuid
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from django.conf import settings
from django.core.files.base import ContentFile
from django.db import IntegrityError, transaction
from django.utils import timezone

from accounts.models import ChainState, Owner, OwnerKey, Robot
from accounts.selectors import (
    owner_by_address,
    owner_by_username,
    owner_key_bytes,
    owner_key_current,
)
from chainworker.chain import AuthROSChain
from chainworker.outbox import enqueue
from chainworker.services import anchor_schedule, chain_client
from sharing.cache import envelope_cache_evict, envelope_cache_put, envelope_fetch
from sharing.errors import (
    AccessDenied,
    AlreadyGranted,
    EnvelopeTooLarge,
    ForgedEnvelope,
    GranteeNotRegistered,
    HeaderMismatch,
    IntegrityCheckFailed,
    InvalidEnvelope,
    NoGrant,
    NotAnchoredYet,
    NotRegisteredYet,
    OwnerNotFound,
    RecordNotFound,
    ReplayedSequence,
    SelfGrant,
    SharingError,
    UnknownKey,
    VerificationUnavailable,
)
from sharing.models import Grant, Record, SecurityEvent, Verdict
from sharing.storage import envelope_storage
from smcrypto import CryptoError, envelope, sm3

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

# An envelope sealed under a key retired less than this long ago is still accepted.
KEY_ROTATION_GRACE = timedelta(hours=1)
MAX_FIELD_LENGTH = 255
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


@dataclass(frozen=True)
class _CheckedUpload:
    record_id: uuid.UUID
    data: bytes
    header: dict
    key: OwnerKey
    captured_at: datetime


def record_create(*, robot: Robot, data: bytes) -> Record:
    """Store one envelope uploaded by `robot`; see `record_create_batch`."""
    return record_create_batch(robot=robot, envelopes=[data])[0]


def record_create_batch(*, robot: Robot, envelopes: Sequence[bytes]) -> list[Record]:
    """Store envelopes uploaded by `robot`, all or none, and queue their anchoring.

    Each must parse, name this robot and its owner, be sealed under the owner's current key
    (or one retired within KEY_ROTATION_GRACE) with a valid tag, and carry a sequence number
    above every earlier one of this robot.
    """
    if not envelopes:
        raise InvalidEnvelope("no envelopes in the upload")
    checked = [_check_upload(robot, data) for data in envelopes]
    seqs = [c.header["seq"] for c in checked]
    if seqs != sorted(set(seqs)):
        raise InvalidEnvelope("sequence numbers in one upload must strictly increase")
    storage = envelope_storage()
    saved: list[str] = []
    try:
        with transaction.atomic():
            locked = Robot.objects.select_for_update().get(pk=robot.pk)
            if seqs[0] <= locked.last_seq:
                raise ReplayedSequence(
                    f"seq {seqs[0]} is not above {locked.last_seq}, the last one of this robot"
                )
            records = []
            for upload in checked:
                name = storage.save(
                    f"{robot.owner_id}/{upload.record_id}.env", ContentFile(upload.data)
                )
                saved.append(name)
                records.append(
                    Record.objects.create(
                        id=upload.record_id,
                        owner_id=robot.owner_id,
                        robot=robot,
                        topic=upload.header["topic"],
                        data_type=upload.header["type"],
                        seq=upload.header["seq"],
                        captured_at=upload.captured_at,
                        key_id=upload.key.key_id,
                        digest=sm3.sm3_hex(upload.data),
                        size=len(upload.data),
                        storage_name=name,
                    )
                )
            Robot.objects.filter(pk=robot.pk).update(last_seq=seqs[-1])
            transaction.on_commit(lambda: _after_upload(robot.owner_id, checked))
    except BaseException:
        # Nothing of a refused or failed upload stays behind, not even its files.
        for name in saved:
            with suppress(OSError):
                storage.delete(name)
        raise
    return records


def _after_upload(owner_id: int, uploads: Sequence[_CheckedUpload]) -> None:
    for upload in uploads:
        envelope_cache_put(upload.record_id, upload.data)
    anchor_schedule(owner_id=owner_id)


def _check_upload(robot: Robot, data: bytes) -> _CheckedUpload:
    if len(data) > settings.ENVELOPE_MAX_BYTES:
        raise EnvelopeTooLarge(
            f"envelope of {len(data)} bytes is above the limit of {settings.ENVELOPE_MAX_BYTES}"
        )
    try:
        info = envelope.read_header(data)
    except CryptoError as exc:
        raise InvalidEnvelope(str(exc)) from None
    header = info.header
    owner = robot.owner
    if header["owner"] != owner.username or header["robot"] != str(robot.id):
        raise HeaderMismatch("the envelope's owner and robot must be this robot's")
    for field in ("topic", "type"):
        if len(header[field]) > MAX_FIELD_LENGTH:
            raise InvalidEnvelope(f"{field} is longer than {MAX_FIELD_LENGTH} characters")
        if "\x00" in header[field]:
            raise InvalidEnvelope(f"{field} contains a NUL character")
    key = owner.keys.filter(key_id=info.key_id.hex()).first()
    grace_start = timezone.now() - KEY_ROTATION_GRACE
    if key is None or not (key.is_current or (key.retired_at and key.retired_at > grace_start)):
        raise UnknownKey("the envelope is not sealed under the owner's current key")
    try:
        envelope.open(owner_key_bytes(key), data)
    except CryptoError:
        SecurityEvent.objects.create(
            kind=SecurityEvent.Kind.FORGED_UPLOAD,
            owner=owner,
            detail={"robot": str(robot.id), "seq": header["seq"], "topic": header["topic"]},
        )
        security_log.warning("forged upload refused: robot %s seq %s", robot.id, header["seq"])
        raise ForgedEnvelope("the envelope does not open under the owner's key") from None
    captured_at = datetime.fromisoformat(header["time"].replace("Z", "+00:00"))
    if captured_at < EPOCH:
        # The chain stores capture times as unsigned microseconds since 1970.
        raise InvalidEnvelope("the capture time must be 1970-01-01T00:00:00Z or later")
    return _CheckedUpload(uuid.uuid4(), bytes(data), header, key, captured_at)


# --- grants ----------------------------------------------------------------------------------


def owner_resolve(identifier: str) -> Owner:
    """An owner named by username or by EOA address."""
    identifier = identifier.strip()
    if identifier.lower().startswith("0x"):
        owner = owner_by_address(identifier)
    else:
        owner = owner_by_username(identifier)
    if owner is None:
        raise OwnerNotFound(f"no owner {identifier!r}")
    return owner


def grant_create(*, owner: Owner, grantee: Owner) -> Grant:
    """Let `grantee` read `owner`'s records; authorityGrant is sent on commit."""
    if grantee.pk == owner.pk:
        raise SelfGrant("an owner always reads its own records")
    if owner.chain_state != ChainState.CONFIRMED:
        raise NotRegisteredYet("your account is not registered on chain yet: try again shortly")
    if grantee.chain_state != ChainState.CONFIRMED:
        raise GranteeNotRegistered(f"{grantee} is not registered on chain yet")
    try:
        with transaction.atomic():
            if Grant.objects.filter(owner=owner, grantee=grantee, status__in=Grant.LIVE).exists():
                raise AlreadyGranted(f"{grantee} already has access")
            grant = Grant.objects.create(owner=owner, grantee=grantee)
            transaction.on_commit(lambda: enqueue("chainworker.tasks.grant_sync", grant.pk))
    except IntegrityError:
        # A simultaneous grant for the same pair won the race (one live grant per pair).
        raise AlreadyGranted(f"{grantee} already has access") from None
    return grant


def grant_revoke(*, owner: Owner, grantee: Owner) -> Grant:
    """Take access away: refused by the portal at once, authorityRevoke sent on commit."""
    with transaction.atomic():
        grant = (
            Grant.objects.select_for_update()
            .filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
            .first()
        )
        if grant is None or grant.status == Grant.Status.REVOKING:
            raise NoGrant(f"{grantee} has no access to revoke")
        grant.status = Grant.Status.REVOKING
        grant.save(update_fields=["status", "updated_at"])
        transaction.on_commit(lambda: enqueue("chainworker.tasks.grant_sync", grant.pk))
    return grant


# --- integrity check at view time ---------------------------------------------------------


@dataclass(frozen=True)
class Verification:
    verdict: Verdict
    envelope: bytes | None  # only when verified


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


# --- reading content -------------------------------------------------------------------------


@dataclass(frozen=True)
class OpenedRecord:
    """A record that passed its integrity check, decrypted for one viewer."""

    record: Record
    verdict: Verdict
    header: dict
    plaintext: bytes
    envelope: bytes


def record_open(*, record_id: uuid.UUID | str, viewer: Owner) -> OpenedRecord:
    """Verify through the worker, then decrypt; raise unless the verdict is `verified`.

    Raises AccessDenied, IntegrityCheckFailed, NotAnchoredYet, RecordNotFound or
    VerificationUnavailable. The bytes decrypted are hashed again here and must be the ones
    the worker checked against the chain.
    """
    try:
        record = Record.objects.select_related("owner__user").get(pk=uuid.UUID(str(record_id)))
    except (ValueError, Record.DoesNotExist):
        raise RecordNotFound("no such record") from None
    return _opened(record, _verdict_from_worker(record, viewer, _send_verify(record, viewer)))


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
            results.append(_opened(record, _verdict_from_worker(record, viewer, pending)))
        except SharingError as exc:
            results.append(exc)
    return results


def _opened(record: Record, verdict: Verdict) -> OpenedRecord:
    if verdict.outcome == Verdict.Outcome.NO_ACCESS:
        raise AccessDenied("you have no live grant to this record")
    if verdict.outcome == Verdict.Outcome.TAMPERED:
        raise IntegrityCheckFailed("the stored data differs from the digest on chain")
    if verdict.outcome == Verdict.Outcome.NOT_ANCHORED_YET:
        raise NotAnchoredYet("the record is not anchored on chain yet")
    data, _source = envelope_fetch(record)
    if sm3.sm3_hex(data) != verdict.chain_digest:
        raise IntegrityCheckFailed("the stored data changed after it was checked")
    key = record.owner.keys.get(key_id=record.key_id)
    header, plaintext = envelope.open(owner_key_bytes(key), data)
    return OpenedRecord(record, verdict, header, plaintext, data)


def record_reseal_for(*, opened: OpenedRecord, viewer: Owner) -> bytes:
    """The record's content sealed under the viewer's own current key (same header)."""
    return envelope.seal(
        owner_key_bytes(owner_key_current(viewer)), opened.header, opened.plaintext
    )


def _send_verify(record: Record, viewer: Owner) -> Any:
    """Queue the worker's integrity check; an exception instead if it cannot be queued."""
    from sharing.tasks import record_verify as record_verify_task  # tasks import services

    try:
        return record_verify_task.apply_async(args=(str(record.pk), viewer.pk))
    except Exception as exc:  # the broker is down
        return exc


def _verdict_from_worker(record: Record, viewer: Owner, pending: Any) -> Verdict:
    try:
        if isinstance(pending, Exception):
            raise pending
        result = pending.get(timeout=settings.VERIFY_TIMEOUT, disable_sync_subtasks=False)
    except Exception as exc:  # timeout, broker down, or the worker's own failure
        logger.warning("verification of %s for %s failed: %s", record.pk, viewer, exc)
        raise VerificationUnavailable(
            "the integrity check could not run now; nothing is shown: try again shortly"
        ) from exc
    return Verdict.objects.get(pk=result["verdict_id"])
