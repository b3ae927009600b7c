"""Exports: the verified records of a selection as an MCAP file, with a proof bundle beside it.

`export_create` checks the selection (what the requester may view: their own records and
those of owners granting them) and queues `export_run` on commit. The worker checks the
records in batches with the view's own integrity check (`records_verify`: access on chain,
the stored envelope's SM3 against the chain, a signed record's robot signature and key, a
Verdict each), leaves out and lists every record that fails, rebuilds the ROS messages of the
others (authros_verify/messages.py, written by sharing/mcap_export.py), and stores the MCAP
file and the bundle in the envelope storage (local disk or S3), for the requester only, until
the export expires.

Each signed record's entry carries its robot's signature, public key and the plaintext it
signed, so that the verifier checks without the portal that each message is the one the robot
signed (a tamperer would need the robot's private key). docs/export.md describes the bundle.
"""

import base64
import logging
import tempfile
import uuid
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta

from django.conf import settings
from django.db import transaction
from django.db.models import QuerySet
from django.utils import timezone

from accounts.errors import IdentityMismatch
from accounts.models import Owner, OwnerKey, Robot
from authros_verify.bundle import BUNDLE_FORMAT, bundle_digest, bundle_serialise
from authros_verify.messages import message_encode, message_log_time
from chainworker.chain import ChainError
from chainworker.services import chain_client
from core.outbox import enqueue
from sharing.disk import disk_room_check
from sharing.errors import (
    ExportExpired,
    ExportNotFound,
    ExportNotReady,
    ExportRefused,
    SharingError,
)
from sharing.mcap_export import McapBuilder
from sharing.models import Access, Export, Record, Verdict
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
from sharing.selectors import export_of, record_list_visible_to, record_proof
from sharing.storage import envelope_storage, envelopes_save
from sharing.verification import RecordKeys, accesses_open, records_verify
from smcrypto import envelope as envelopes
from smcrypto import provenance, sm2
from smcrypto.errors import CryptoError
from smcrypto.sm3 import sm3_hex

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


def export_create(
    *,
    requester: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
) -> Export:
    """Check the selection (robots and topics, empty: all; capture times [since, until)) and
    queue its export; ExportRefused if it cannot be exported."""
    try:
        selection = RecordSelection.of(robots=robots, topics=topics, since=since, until=until)
    except SelectionError as exc:
        raise ExportRefused(_SELECTION_REFUSALS.get(exc.rule, str(exc))) from None
    visible = set(export_robots_visible(requester).values_list("pk", flat=True))
    unknown = [str(robot) for robot in selection.robots if robot not in visible]
    if unknown:
        raise ExportRefused(f"no robot whose records you may view has the id {unknown[0]}")
    count = export_records(requester, selection).count()
    if count == 0:
        raise ExportRefused("no record you may view is in this selection")
    if count > settings.EXPORT_MAX_RECORDS:
        raise ExportRefused(
            f"the selection holds {count} records; an export takes at most "
            f"{settings.EXPORT_MAX_RECORDS}: choose fewer robots, topics or a shorter time range"
        )
    with transaction.atomic():
        export = Export.objects.create(
            requester=requester,
            selection=selection.as_json(),
            total=count,
            expires_at=timezone.now() + timedelta(hours=settings.EXPORT_TTL_HOURS),
        )
        transaction.on_commit(lambda: enqueue(EXPORT_TASK, str(export.pk)))
    return export


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
    export.refresh_from_db()
    return export


def _run(export: Export) -> None:
    selection = RecordSelection.from_json(export.selection)
    records = list(
        export_records(export.requester, selection).select_related(
            "owner__user", "anchor_root", "robot"
        )
    )
    Export.objects.filter(pk=export.pk).update(
        status=Export.Status.RUNNING, total=len(records), processed=0, exported=0
    )
    client = chain_client()
    chain_id, contract = client.chain_id, client.address
    keys = RecordKeys()
    # The export is one line of the access log per record owner, its batches' verdicts under it.
    accesses = accesses_open(
        kind=Access.Kind.EXPORT,
        viewer_id=export.requester.pk,
        records=records,
        credential=Verdict.Credential.UNKNOWN,
        token_id=None,
    )
    entries: list[dict] = []
    excluded: list[dict] = []
    with tempfile.TemporaryFile() as output:
        builder = McapBuilder(output)
        batch_size = settings.EXPORT_BATCH
        for start in range(0, len(records), batch_size):
            batch = records[start : start + batch_size]
            for record, checked, reason in _verified(batch, export.requester, accesses):
                if reason:
                    excluded.append(_excluded(record, reason))
                    continue
                try:
                    entry = _exported(record, checked, keys, builder, len(entries) + 1)
                except _SignerUnknown as exc:
                    logger.warning("export %s: record %s left out: %s", export.pk, record.pk, exc)
                    excluded.append(_excluded(record, SIGNATURE_REFUSED))
                    continue
                except (SharingError, OwnerKey.DoesNotExist, CryptoError) as exc:
                    logger.warning("export %s: record %s not opened: %s", export.pk, record.pk, exc)
                    excluded.append(_excluded(record, "cannot_open"))
                    continue
                entries.append(
                    {**record_proof(record, chain_id=chain_id, contract=contract), **entry}
                )
            Export.objects.filter(pk=export.pk).update(
                processed=start + len(batch), exported=len(entries)
            )
        builder.finish()
        output.seek(0)
        mcap = output.read()
    mcap_name = f"authros-export-{str(export.pk)[:8]}.mcap"
    document = {
        "format": BUNDLE_FORMAT,
        "export": str(export.pk),
        "created_at": iso_utc(export.created_at),
        "requested_by": export.requester.username,
        "selection": export.selection,
        "chain_id": chain_id,
        "contract": contract,
        "mcap": {"name": mcap_name, "size": len(mcap), "sm3": "0x" + sm3_hex(mcap)},
        "records": entries,
        "excluded": excluded,
    }
    document["bundle_sm3"] = bundle_digest(document)
    bundle = bundle_serialise(document)
    folder = f"{EXPORT_STORAGE_PREFIX}/{export.pk}"
    files = [(f"{folder}/{mcap_name}", mcap), (f"{folder}/proofs.json", bundle)]
    disk_room_check(sum(len(data) for _name, data in files))
    storage = envelope_storage()
    for name, _data in files:  # left by a run that stopped before it finished (a redelivery)
        storage.delete(name)
    names = envelopes_save(storage, files)
    _finish(
        export,
        status=Export.Status.DONE,
        exported=len(entries),
        processed=len(records),
        excluded=excluded,
        mcap_name=names[0],
        bundle_name=names[1],
        mcap_size=len(mcap),
        bundle_size=len(bundle),
        mcap_sm3=sm3_hex(mcap),
    )


def _verified(
    batch: Sequence[Record], requester: Owner, accesses: dict[int, int]
) -> list[tuple[Record, bytes | None, str]]:
    """Each record of the batch with the envelope the check let through, or why it did not:
    one run of the view's check for the whole batch."""
    unanchored = [record for record in batch if record.status != Record.Status.ANCHORED]
    wanted = [record for record in batch if record.status == Record.Status.ANCHORED]
    answers: dict[uuid.UUID, tuple[bytes | None, str]] = {
        record.pk: (None, NOT_ANCHORED) for record in unanchored
    }
    if wanted:
        try:
            checked = records_verify(
                record_ids=[r.pk for r in wanted], viewer_id=requester.pk, accesses=accesses
            )
        except IdentityMismatch:
            checked = []
            answers.update({r.pk: (None, "identity_check_failed") for r in wanted})
        for verification in checked:
            outcome = verification.verdict.outcome
            reason = "" if outcome == Verdict.Outcome.VERIFIED else REASONS.get(outcome, outcome)
            answers[verification.verdict.record_id] = (verification.envelope, reason)
    return [(record, *answers.get(record.pk, (None, "not_found"))) for record in batch]


def _exported(
    record: Record, data: bytes, keys: RecordKeys, builder: McapBuilder, sequence: int
) -> dict[str, object]:
    """Write the record's message into the MCAP file; its bundle entry but the proof."""
    header, plaintext = envelopes.open(keys.of(record), data)
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


# --- downloads and expiry ------------------------------------------------------------------------


def exports_sweep() -> dict[str, int]:
    """The periodic job: queue again exports whose message was lost (queued for longer than
    EXPORT_REQUEUE_AFTER seconds: a broker that was down), and expire old ones."""
    stale = timezone.now() - timedelta(seconds=settings.EXPORT_REQUEUE_AFTER)
    requeued = 0
    for export_id in Export.objects.filter(
        status=Export.Status.QUEUED, created_at__lt=stale, expires_at__gt=timezone.now()
    ).values_list("pk", flat=True):
        requeued += enqueue(EXPORT_TASK, str(export_id))
    return {"requeued": requeued, "expired": exports_expire()}


def exports_expire() -> int:
    """Remove the files of exports past their expiry; how many expired."""
    storage = envelope_storage()
    expired = Export.objects.filter(expires_at__lte=timezone.now()).exclude(
        status=Export.Status.EXPIRED
    )
    count = 0
    for export in expired:
        for name in (export.mcap_name, export.bundle_name):
            if name:
                storage.delete(name)
        Export.objects.filter(pk=export.pk).update(status=Export.Status.EXPIRED)
        count += 1
    return count


def export_download(*, requester: Owner, export_id: uuid.UUID | str, part: str) -> tuple[str, str]:
    """(storage name, file name) of an export's MCAP file (`part` "mcap") or proof bundle
    ("bundle"), for its requester only; ExportNotFound, ExportNotReady or ExportExpired."""
    export = export_of(requester, export_id)
    if export is None:
        raise ExportNotFound("no such export of yours")
    if export.status == Export.Status.EXPIRED or export.expires_at <= timezone.now():
        raise ExportExpired("this export has expired and its files are removed; export again")
    if export.status != Export.Status.DONE:
        raise ExportNotReady("this export is not ready yet")
    stem = f"authros-export-{str(export.pk)[:8]}"
    if part == "mcap":
        return export.mcap_name, f"{stem}.mcap"
    return export.bundle_name, f"{stem}.proofs.json"


def _micros(moment: datetime) -> int:
    delta = moment - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
