"""Exports: the verified records of a selection as an MCAP file, with a proof bundle beside it.

`export_create` checks the selection (what the requester may view: their own records and
those of owners granting them; at most EXPORT_MAX_RECORDS, `export_count` says how many before
submitting) and queues `export_run` on commit. The worker reads the records EXPORT_BATCH at a
time and checks each batch with the view's own integrity check (`_verified`, the one use of
`records_verify`: access on chain, the stored envelope's SM3 against the chain, a signed
record's robot signature and key, a Verdict each), leaves out and lists every record that
fails, rebuilds the ROS messages of the others (authros_verify/messages.py, written by
sharing/mcap_export.py) and writes both files as it goes, in constant memory, sealed
(smcrypto/stream.py) under a key of the export's own wrapped by the KEK: nothing of an export
is plaintext at rest, in the envelope storage (local disk or S3) or in its backups.

The files are decrypted only while streamed to the requester, and only while the requester
may still view every record in them (`ExportRecord` lists them): a revocation, a changed or
expired grant, a deleted record or a closed account withdraws the export, removing its key and
its files (`export_access_lost`, checked at every download and look, and by `exports_recheck`).

Each signed record's entry carries its robot's signature, public key and the plaintext it
signed, so that the verifier checks without the portal that each message is the one the robot
signed (a tamperer would need the robot's private key). docs/export.md describes the bundle.
"""

import base64
import logging
import tempfile
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import IO

from django.conf import settings
from django.db import transaction
from django.db.models import Q, QuerySet
from django.utils import timezone

from accounts.errors import IdentityMismatch
from accounts.keywrap import UnwrapFailed, unwrap, wrap
from accounts.models import Owner, OwnerKey, OwnerToken, Robot
from authros_verify.bundle import BUNDLE_FORMAT, bundle_entry_line, bundle_write
from authros_verify.messages import message_encode, message_log_time
from chainworker.errors import ChainError
from chainworker.services import chain_client
from core.outbox import enqueue
from sharing.disk import disk_room_check
from sharing.errors import (
    ExportExpired,
    ExportNotFound,
    ExportNotReady,
    ExportRefused,
    ExportWithdrawn,
    SharingError,
)
from sharing.mcap_export import McapBuilder
from sharing.models import Access, Export, ExportRecord, Grant, Record, Verdict
from sharing.selection import (
    MAX_SELECTED_ROBOTS,
    MAX_SELECTED_TOPICS,
    TOO_MANY_ROBOTS,
    TOO_MANY_TOPICS,
    WINDOW_NOT_ORDERED,
    RecordSelection,
    SelectionError,
    iso_utc,
)
from sharing.selectors import (
    export_of,
    grant_live,
    record_list_visible_to,
    record_proof,
    records_to_check,
)
from sharing.storage import envelope_storage, file_save
from sharing.verification import (
    OwnerRead,
    RecordKeys,
    Verification,
    accesses_open_for,
    records_verify,
)
from smcrypto import envelope as envelopes
from smcrypto import provenance, sm2, sm4
from smcrypto.errors import CryptoError
from smcrypto.sm3 import sm3_hasher, sm3_hex
from smcrypto.stream import SealedWriter, sealed_open

logger = logging.getLogger(__name__)

EXPORT_TASK = "sharing.tasks.export_run"
EXPORT_STORAGE_PREFIX = "exports"
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
# An export's own words for these refusals of its selection; the others keep the selection's.
_TOO_MANY = f"select at most {MAX_SELECTED_ROBOTS} robots and {MAX_SELECTED_TOPICS} topics"
_SELECTION_REFUSALS = {
    TOO_MANY_ROBOTS: _TOO_MANY,
    TOO_MANY_TOPICS: _TOO_MANY,
    WINDOW_NOT_ORDERED: "the start of the time range is not before its end",
}

# Why a record is left out of an export (its entry in `excluded`).
NOT_ANCHORED = "not_anchored_yet"
SIGNATURE_REFUSED = "signature_refused"
REASONS = {
    Verdict.Outcome.TAMPERED: "integrity_check_failed",
    Verdict.Outcome.NO_ACCESS: "access_denied",
    Verdict.Outcome.NOT_ANCHORED_YET: NOT_ANCHORED,
    Verdict.Outcome.SIGNATURE_REFUSED: SIGNATURE_REFUSED,
}


class _SignerUnknown(Exception):
    """The robot's public key on record is not the key that signed the record."""


def export_robots_visible(requester: Owner) -> QuerySet[Robot]:
    """The robots whose records the requester may view (own, and of owners granting them)."""
    visible = record_list_visible_to(requester)
    return Robot.objects.filter(pk__in=visible.values("robot_id")).select_related("owner__user")


def export_topics_visible(requester: Owner) -> list[str]:
    visible = record_list_visible_to(requester).order_by("topic")
    return list(visible.values_list("topic", flat=True).distinct())


def export_records(requester: Owner, selection: RecordSelection) -> QuerySet[Record]:
    """The records of the selection the requester may view, in capture order; deleted ones
    are left out (their data is gone), not listed as excluded."""
    records = record_list_visible_to(requester).filter(deleted_at__isnull=True)
    return selection.apply(records).order_by("captured_at", "seq", "id")


def export_count(
    *,
    requester: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
) -> "ExportCount":
    """How many records the selection holds that the requester may view, and whether that is
    within EXPORT_MAX_RECORDS; ExportRefused for a selection that cannot be asked for."""
    selection = _selection_checked(
        requester, robots=robots, topics=topics, since=since, until=until
    )
    count = export_records(requester, selection).count()
    return ExportCount(selection=selection, count=count, limit=settings.EXPORT_MAX_RECORDS)


@dataclass(frozen=True)
class ExportCount:
    selection: RecordSelection
    count: int
    limit: int

    @property
    def refusal(self) -> str:
        """Why this selection is not exported, or "" when it is."""
        if self.count == 0:
            return "no record you may view is in this selection"
        if self.count > self.limit:
            return (
                f"the selection holds {self.count:,} records; an export takes at most "
                f"{self.limit:,}: choose fewer robots, topics or a shorter time range"
            )
        return ""


def _selection_checked(
    requester: Owner,
    *,
    robots: Sequence[uuid.UUID | str],
    topics: Sequence[str],
    since: datetime | None,
    until: datetime | None,
) -> RecordSelection:
    try:
        selection = RecordSelection.of(robots=robots, topics=topics, since=since, until=until)
    except SelectionError as exc:
        raise ExportRefused(_SELECTION_REFUSALS.get(exc.rule, str(exc))) from None
    visible = set(export_robots_visible(requester).values_list("pk", flat=True))
    unknown = [str(robot) for robot in selection.robots if robot not in visible]
    if unknown:
        raise ExportRefused(f"no robot whose records you may view has the id {unknown[0]}")
    return selection


def export_create(
    *,
    requester: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
    credential: str = Verdict.Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> Export:
    """Check the selection (robots and topics, empty: all; capture times [since, until)) and
    queue its export; ExportRefused if it cannot be exported (its count says why). The
    credential (and token) that asked is what its access-log lines record."""
    counted = export_count(
        requester=requester, robots=robots, topics=topics, since=since, until=until
    )
    if counted.refusal:
        raise ExportRefused(counted.refusal)
    with transaction.atomic():
        export = Export.objects.create(
            requester=requester,
            credential=credential,
            token=token,
            selection=counted.selection.as_json(),
            total=counted.count,
            expires_at=timezone.now() + timedelta(hours=settings.EXPORT_TTL_HOURS),
        )
        transaction.on_commit(lambda: enqueue(EXPORT_TASK, str(export.pk)))
    return export


def export_selection_described(export: Export) -> dict[str, object]:
    """The export's selection in words for its page: robots by name, topics, the window, and
    the command that checks its files against its chain (docs/export.md)."""
    selection = RecordSelection.from_json(export.selection)
    robots = Robot.objects.filter(pk__in=selection.robots).select_related("owner__user")
    names = {robot.pk: f"{robot.name} ({robot.owner.username})" for robot in robots}
    stem = export_file_stem(export)
    command = [
        "authros-verify",
        f"{stem}.proofs.json",
        f"--mcap {stem}.mcap",
        "--rpc RPC_URL",
    ]
    if export.contract:
        command.append(f"--contract {export.contract}")
    if export.chain_id is not None:
        command.append(f"--chain-id {export.chain_id}")
    return {
        "robots": [names.get(robot, str(robot)) for robot in selection.robots],
        "topics": list(selection.topics),
        "since": iso_utc(selection.since),
        "until": iso_utc(selection.until),
        "verify_command": " ".join(command),
    }


def export_file_stem(export: Export) -> str:
    """The files' names as downloaded: `<stem>.mcap` and `<stem>.proofs.json`."""
    return f"authros-export-{str(export.pk)[:8]}"


def export_rebuild(
    *,
    requester: Owner,
    export_id: uuid.UUID | str,
    credential: str = Verdict.Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> Export:
    """A new export of an export's selection, made under the requester's access now, asked
    for by `credential`."""
    export = export_of(requester, export_id)
    if export is None:
        raise ExportNotFound("no such export of yours")
    selection = RecordSelection.from_json(export.selection)
    return export_create(
        requester=requester,
        robots=selection.robots,
        topics=selection.topics,
        since=selection.since,
        until=selection.until,
        credential=credential,
        token=token,
    )


# --- the export, on a worker -------------------------------------------------------------------


def export_run(*, export_id: uuid.UUID | str) -> Export:
    """Check, rebuild and store the export's records; the Export says how it went."""
    export = Export.objects.select_related("requester__user").get(pk=export_id)
    if export.status not in (Export.Status.QUEUED, Export.Status.RUNNING):
        return export  # done already (a message delivered twice)
    try:
        _run(export)
    except (ChainError, SharingError, OSError) as exc:
        logger.warning("export %s failed: %s", export.pk, exc)
        _finish(export, status=Export.Status.FAILED, error=f"the export could not finish: {exc}")
    except Exception:
        logger.exception("export %s failed", export.pk)
        _finish(export, status=Export.Status.FAILED, error="the export failed; this was logged")
        raise
    finally:
        if Export.objects.filter(pk=export.pk, status=Export.Status.FAILED).exists():
            ExportRecord.objects.filter(export=export).delete()
    export.refresh_from_db()
    return export


def export_batches(records: QuerySet[Record], size: int) -> Iterator[list[Record]]:
    """The records in capture order, `size` at a time: one batch in memory, never the whole
    selection (keyset pagination on the export's order, so no batch is read twice)."""
    after: Q | None = None
    while True:
        page = records if after is None else records.filter(after)
        batch = list(page[:size])
        if not batch:
            return
        yield batch
        last = batch[-1]
        # The leading `>=` lets the database seek to the batch in its (owner, captured_at)
        # index rather than read every earlier record again for each batch.
        after = Q(captured_at__gte=last.captured_at) & (
            Q(captured_at__gt=last.captured_at)
            | Q(captured_at=last.captured_at, seq__gt=last.seq)
            | Q(captured_at=last.captured_at, seq=last.seq, id__gt=last.id)
        )


class _SealedOutput:
    """A file written as plaintext, stored sealed: the bytes are hashed (SM3) and counted on
    their way into a SealedWriter (smcrypto/stream.py). `tell` is the plaintext's, as the MCAP
    writer asks for its offsets."""

    def __init__(self, target: IO[bytes], key: bytes) -> None:
        self.sealed = SealedWriter(target, key)
        self._sm3 = sm3_hasher()

    def write(self, data: bytes) -> int:
        self._sm3.update(data)
        return self.sealed.write(data)

    def tell(self) -> int:
        return self.sealed.written

    def flush(self) -> None:
        """Nothing to flush: a segment is sealed as soon as it is full."""

    def close(self) -> tuple[int, str]:
        """Seal the last segment; (plaintext size, its SM3 in hex)."""
        self.sealed.close()
        return self.sealed.written, self._sm3.finalize().hex()


def _run(export: Export) -> None:
    selection = RecordSelection.from_json(export.selection)
    records = records_to_check(export_records(export.requester, selection))
    total = records.count()
    ExportRecord.objects.filter(export=export).delete()  # left by a run that stopped midway
    Export.objects.filter(pk=export.pk).update(
        status=Export.Status.RUNNING, total=total, processed=0, exported=0
    )
    client = chain_client()
    chain_id, contract = client.chain_id, client.address
    key = sm4.generate_key()
    keys = RecordKeys()
    # The export is one line of the access log per record owner, its batches' verdicts under it.
    accesses = accesses_open_for(
        kind=Access.Kind.EXPORT,
        viewer_id=export.requester.pk,
        reads=_owner_reads(records),
        credential=export.credential,
        token_id=export.token_id,
    )
    excluded: list[dict] = []
    exported = processed = 0
    mcap_name = f"authros-export-{str(export.pk)[:8]}.mcap"
    with (
        tempfile.TemporaryFile() as mcap_file,
        tempfile.TemporaryFile() as bundle_file,
        tempfile.TemporaryFile(mode="w+", encoding="ascii") as entries,
    ):
        mcap = _SealedOutput(mcap_file, key)
        builder = McapBuilder(mcap)
        for batch in export_batches(records, settings.EXPORT_BATCH):
            inside: list[ExportRecord] = []
            for record, checked, reason in _verified(batch, export.requester, accesses):
                if reason:
                    excluded.append(_excluded(record, reason))
                    continue
                try:
                    entry = _exported(record, checked, keys, builder, exported + 1)
                except _SignerUnknown as exc:
                    logger.warning("export %s: record %s left out: %s", export.pk, record.pk, exc)
                    excluded.append(_excluded(record, SIGNATURE_REFUSED))
                    continue
                except (SharingError, OwnerKey.DoesNotExist, CryptoError) as exc:
                    logger.warning("export %s: record %s not opened: %s", export.pk, record.pk, exc)
                    excluded.append(_excluded(record, "cannot_open"))
                    continue
                proof = record_proof(record, chain_id=chain_id, contract=contract)
                entries.write(bundle_entry_line({**proof, **entry}) + "\n")
                inside.append(ExportRecord(export=export, record=record))
                exported += 1
            ExportRecord.objects.bulk_create(inside)
            processed += len(batch)
            Export.objects.filter(pk=export.pk).update(processed=processed, exported=exported)
        builder.finish()
        mcap_size, mcap_sm3 = mcap.close()
        head = {
            "format": BUNDLE_FORMAT,
            "export": str(export.pk),
            "created_at": iso_utc(export.created_at),
            "requested_by": export.requester.username,
            "selection": export.selection,
            "chain_id": chain_id,
            "contract": contract,
            "mcap": {"name": mcap_name, "size": mcap_size, "sm3": "0x" + mcap_sm3},
            "excluded": excluded,
        }
        bundle = _SealedOutput(bundle_file, key)
        bundle_write(head, lambda: _lines(entries), bundle)
        bundle_size, _bundle_sm3 = bundle.close()
        folder = f"{EXPORT_STORAGE_PREFIX}/{export.pk}"
        files = [
            (f"{folder}/{mcap_name}.sealed", mcap_file),
            (f"{folder}/proofs.json.sealed", bundle_file),
        ]
        disk_room_check(mcap.sealed.sealed_size + bundle.sealed.sealed_size)
        # Wrapped before anything is stored: no file is ever kept without its key.
        key_wrapped = wrap(key, purpose=export_key_purpose(export.pk))
        storage = envelope_storage()
        names = []
        for name, sealed in files:
            storage.delete(name)  # left by a run that stopped before it finished (a redelivery)
            names.append(file_save(storage, name, sealed))
    _finish(
        export,
        status=Export.Status.DONE,
        exported=exported,
        processed=processed,
        excluded=excluded,
        mcap_name=names[0],
        bundle_name=names[1],
        mcap_size=mcap_size,
        bundle_size=bundle_size,
        mcap_sm3=mcap_sm3,
        key_wrapped=key_wrapped,
        chain_id=chain_id,
        contract=contract,
    )


def _lines(spool: IO[str]) -> Iterator[str]:
    """The bundle entries spooled to disk, one a line, from the first."""
    spool.seek(0)
    for line in spool:
        yield line.rstrip("\n")


def _owner_reads(records: QuerySet[Record]) -> list[OwnerRead]:
    """What the export reads of each owner's records, counted in the database (the records
    themselves are read batch by batch, never all at once)."""
    reads = []
    for owner_id in records.order_by().values_list("owner_id", flat=True).distinct():
        theirs = records.filter(owner_id=owner_id).order_by()
        count = theirs.count()
        robots = list(theirs.values_list("robot_id", flat=True).distinct()[:2])
        topics = list(theirs.values_list("topic", flat=True).distinct()[:2])
        reads.append(
            OwnerRead(
                owner_id=owner_id,
                count=count,
                record=theirs.first() if count == 1 else None,
                robot_id=robots[0] if len(robots) == 1 else None,
                topic=topics[0] if len(topics) == 1 else None,
            )
        )
    return reads


def export_key_purpose(export_id: uuid.UUID | str) -> str:
    return f"export-key:{export_id}"


def _verified(
    batch: Sequence[Record], requester: Owner, accesses: dict[int, int]
) -> list[tuple[Record, Verification | None, str]]:
    """Each record of the batch with its check when it let the record through, or why it did
    not: one run of the view's check for the whole batch, on the records as read."""
    unanchored = [record for record in batch if record.status != Record.Status.ANCHORED]
    wanted = [record for record in batch if record.status == Record.Status.ANCHORED]
    answers: dict[uuid.UUID, tuple[Verification | None, str]] = {
        record.pk: (None, NOT_ANCHORED) for record in unanchored
    }
    if wanted:
        try:
            checked = records_verify(records=wanted, viewer_id=requester.pk, accesses=accesses)
        except IdentityMismatch:
            checked = []
            answers.update({r.pk: (None, "identity_check_failed") for r in wanted})
        for verification in checked:
            outcome = verification.verdict.outcome
            if outcome == Verdict.Outcome.VERIFIED:
                answers[verification.verdict.record_id] = (verification, "")
            else:
                answers[verification.verdict.record_id] = (None, REASONS.get(outcome, outcome))
    return [(record, *answers.get(record.pk, (None, "not_found"))) for record in batch]


def _exported(
    record: Record, checked: Verification, keys: RecordKeys, builder: McapBuilder, sequence: int
) -> dict[str, object]:
    """Write the record's message into the MCAP file; its bundle entry but the proof. The
    envelope is the one the check let through, as the check opened it (a signed record's)."""
    data = checked.envelope
    header, plaintext = checked.opened or envelopes.open(keys.of(record), data)
    message = message_encode(data_type=header["type"], plaintext=plaintext)
    log_time = message_log_time(message, _micros(record.captured_at) * 1000)
    signature = _signature(record, header)
    builder.add(topic=record.topic, message=message, log_time=log_time, sequence=sequence)
    return {
        "robot": str(record.robot_id),
        "topic": record.topic,
        "type": record.data_type,
        "seq": record.seq,
        "captured_at": header["time"],
        "envelope": base64.b64encode(data).decode("ascii"),
        "signature": signature,
        # What the robot signed, so that anyone checks the signature and rebuilds the message.
        "plaintext": None if signature is None else base64.b64encode(plaintext).decode("ascii"),
        "mcap": {
            "topic": record.topic,
            "sequence": sequence,
            "log_time": log_time,
            "publish_time": log_time,
            "message_encoding": message.message_encoding,
            "schema": message.schema_name,
            "sm3": "0x" + sm3_hex(message.data),
        },
    }


def _signature(record: Record, header: dict) -> dict[str, str] | None:
    """The robot's signature as the envelope's header carries it, with the robot's public key
    (04||x||y); None for an unsigned record (a robot added by hand)."""
    signer = header.get("signer")
    if not signer:
        return None
    public_key = record.robot.public_key
    if not public_key or provenance.key_hash(public_key) != signer:
        raise _SignerUnknown(f"the robot's public key is not the signer {signer}")
    return {
        "signer": signer,
        "sig": header["sig"],
        "public_key": sm2.public_key_normalize(public_key),
    }


def _excluded(record: Record, reason: str) -> dict[str, str]:
    return {
        "record": str(record.pk),
        "topic": record.topic,
        "captured_at": iso_utc(record.captured_at),
        "reason": reason,
    }


def _finish(export: Export, *, status: str, **fields: object) -> None:
    Export.objects.filter(pk=export.pk).update(status=status, finished_at=timezone.now(), **fields)


# --- access, downloads and expiry ---------------------------------------------------------------


def exports_sweep() -> dict[str, int]:
    """The periodic job: queue again exports whose message was lost (queued for longer than
    EXPORT_REQUEUE_AFTER seconds: a broker that was down), expire old ones, and withdraw the
    ones whose requester may no longer view every record in them (a grant that expired)."""
    stale = timezone.now() - timedelta(seconds=settings.EXPORT_REQUEUE_AFTER)
    requeued = 0
    for export_id in Export.objects.filter(
        status=Export.Status.QUEUED, created_at__lt=stale, expires_at__gt=timezone.now()
    ).values_list("pk", flat=True):
        requeued += enqueue(EXPORT_TASK, str(export_id))
    expired = exports_expire()
    return {"requeued": requeued, "expired": expired, "withdrawn": exports_recheck()}


def exports_expire() -> int:
    """Remove the files of exports past their expiry; how many expired."""
    expired = Export.objects.filter(expires_at__lte=timezone.now()).exclude(
        status__in=[Export.Status.EXPIRED, Export.Status.WITHDRAWN]
    )
    count = 0
    for export in expired:
        _files_remove(export, status=Export.Status.EXPIRED, reason=None)
        count += 1
    return count


def exports_recheck(*, owner_id: int | None = None) -> int:
    """Withdraw each ready export whose requester may no longer view every record in it: of
    `owner_id`'s records or asked for by them (after a revocation, a changed grant, a
    deletion, a closed account), or every ready export (the sweep). How many were withdrawn."""
    ready = Export.objects.filter(status=Export.Status.DONE).select_related("requester__user")
    if owner_id is not None:
        ready = ready.filter(
            Q(requester_id=owner_id)
            | Q(pk__in=ExportRecord.objects.filter(record__owner_id=owner_id).values("export_id"))
        )
    withdrawn = 0
    for export in ready:
        withdrawn += _still_allowed(export) is not None
    return withdrawn


def export_access_lost(export: Export) -> str:
    """Why the export's requester may no longer have it, or "" while they may view every
    record in it (record_list_visible_to: their own, and others' inside a live grant's scope)
    and none of them is deleted."""
    if export.requester.deleted_at is not None:
        return "your account is closed"
    if not export.key_wrapped:
        # Made before exports were sealed: plaintext at rest, which must not stay.
        return "it was stored before exports were sealed; export again"
    contents = ExportRecord.objects.filter(export=export)
    ids = contents.values("record_id")
    inside = record_list_visible_to(export.requester).filter(pk__in=ids, deleted_at__isnull=True)
    if inside.count() == contents.count():
        return ""
    if Record.objects.filter(pk__in=ids, deleted_at__isnull=False).exists():
        return "a record in it was deleted, and its data with it"
    others = Record.objects.filter(pk__in=ids).exclude(owner_id=export.requester_id)
    grants = {}
    for owner_id in others.values_list("owner_id", flat=True).distinct():
        grants[owner_id] = grant_live(owner_id=owner_id, viewer=export.requester)
        if grants[owner_id] is None:
            return _grant_ended(owner_id, export.requester)
    for owner_id, grant in grants.items():
        theirs = others.filter(owner_id=owner_id)
        if grant.scope.apply(theirs).count() != theirs.count():
            return f"{grant.owner.username} narrowed your grant: records in it are outside it now"
    return "you may no longer view every record in it"


def _grant_ended(owner_id: int, requester: Owner) -> str:
    last = (
        Grant.objects.filter(owner_id=owner_id, grantee=requester)
        .select_related("owner__user")
        .order_by("-created_at")
        .first()
    )
    if last is None:
        return "you no longer have access to records in it"
    name = last.owner.username
    if last.status in (Grant.Status.REVOKING, Grant.Status.REVOKED):
        return f"{name} revoked your access to their records"
    if last.expires_at is not None and last.expires_at <= timezone.now():
        return f"your grant from {name} expired at {iso_utc(last.expires_at)}"
    return f"your access to {name}'s records is not live"


def _still_allowed(export: Export) -> str | None:
    """None while the export may be downloaded; else withdraw it (files and key gone) and
    answer why."""
    reason = export_access_lost(export)
    if not reason:
        return None
    _files_remove(export, status=Export.Status.WITHDRAWN, reason=f"withdrawn: {reason}")
    return reason


def _files_remove(export: Export, *, status: str, reason: str | None) -> None:
    """The export's key first (a copy of its files, a backup, opens no more), then its files
    and its list of records; `reason`, if any, is shown as why."""
    said = {} if reason is None else {"error": reason}
    Export.objects.filter(pk=export.pk).update(status=status, key_wrapped=b"", **said)
    storage = envelope_storage()
    for name in (export.mcap_name, export.bundle_name):
        if name:
            storage.delete(name)
    ExportRecord.objects.filter(export=export).delete()


@dataclass(frozen=True)
class ExportFile:
    """One of an export's files, to stream to its requester: `chunks()` decrypts it as read."""

    name: str
    filename: str
    size: int
    key: bytes

    def chunks(self) -> Iterator[bytes]:
        with envelope_storage().open(self.name, "rb") as sealed:
            yield from sealed_open(sealed, self.key)


def export_download(*, requester: Owner, export_id: uuid.UUID | str, part: str) -> ExportFile:
    """An export's MCAP file (`part` "mcap") or proof bundle ("bundle"), for its requester
    only, while they may view every record in it; ExportNotFound, ExportNotReady,
    ExportExpired or ExportWithdrawn (nothing is streamed then)."""
    export = export_current(requester=requester, export_id=export_id)
    if export.status == Export.Status.WITHDRAWN:
        raise ExportWithdrawn(f"this export is {export.error}; its files are removed")
    if export.status == Export.Status.EXPIRED or export.expires_at <= timezone.now():
        raise ExportExpired("this export has expired and its files are removed; export again")
    if export.status != Export.Status.DONE:
        raise ExportNotReady("this export is not ready yet")
    try:
        key = unwrap(bytes(export.key_wrapped), purpose=export_key_purpose(export.pk))
    except UnwrapFailed:
        raise ExportWithdrawn("this export's key is gone; export again") from None
    stem = export_file_stem(export)
    if part == "mcap":
        return ExportFile(export.mcap_name, f"{stem}.mcap", export.mcap_size, key)
    return ExportFile(export.bundle_name, f"{stem}.proofs.json", export.bundle_size, key)


def export_current(*, requester: Owner, export_id: uuid.UUID | str) -> Export:
    """The requester's export as it stands now: a ready one whose records they may no longer
    all view is withdrawn first. ExportNotFound if it is not theirs."""
    export = export_of(requester, export_id)
    if export is None:
        raise ExportNotFound("no such export of yours")
    if export.status == Export.Status.DONE and _still_allowed(export) is not None:
        export.refresh_from_db()
    return export


def _micros(moment: datetime) -> int:
    delta = moment - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
