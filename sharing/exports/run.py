"""An export made, on a worker: the records read EXPORT_BATCH at a time and checked with the
view's own integrity check (`_verified`, the one use of records_verify: access on chain, the
stored envelope's SM3 against the chain, a signed record's robot signature and key, a Verdict
each, all under the export's access-log lines), every record that fails left out and listed,
the ROS messages of the others rebuilt (authros_verify/messages.py, written by
sharing/mcap_export.py) and both files written as it goes, in constant memory, sealed
(smcrypto/stream.py) under a key of the export's own wrapped by the KEK.

Each signed record's entry carries its robot's signature facts (sharing.verification.signature)
and the plaintext it signed, so that the verifier checks without the portal that each message
is the one the robot signed; a record signed in a batch (provenance v2) also its topic_seq and
its place in the batch, as its anchored envelope states them. The bundle carries the portal's
completeness of the selection (sharing.selectors.completeness, tombstones included, so that a
deletion or a retention sweep is named with its reason), and each record left out names its
stream and number, so that the verifier names the gap it leaves. docs/export.md describes the
bundle.

Each distinct batch signature is verified once per export batch (EXPORT_BATCH records): the
check (records_verify) hands the whole batch to provenance.claims_hold, which verifies each
distinct claim once; an upload batch cut by an export batch's edge is verified once on each
side.

The check and the writing run side by side (issue 45): while batch k+1 is checked here, a
forked process (`_Encoder`) makes batch k's ROS messages and bundle lines from its records as
the check opened them; they are written here, in order. The forked process has no database,
key or file of its own to touch; every record is still checked as a view checks it.
"""

import base64
import logging
import multiprocessing
import os
import tempfile
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from typing import IO, Any

from django.conf import settings
from django.db.models import Q, QuerySet
from django.utils import timezone

from accounts.errors import IdentityMismatch
from accounts.keywrap import wrap
from accounts.models import Owner, OwnerKey
from authros_verify.bundle import BUNDLE_FORMAT, bundle_entry_line, bundle_write
from authros_verify.messages import EncodedMessage, message_encode, message_log_time
from chainworker.errors import ChainError
from chainworker.services import chain_client
from core.rows import FixedInsert
from sharing.disk import disk_room_check
from sharing.errors import SharingError
from sharing.exports.files import EXPORT_STORAGE_PREFIX, export_file_stem, export_key_purpose
from sharing.exports.selection import export_records, export_streams
from sharing.mcap_export import McapBuilder
from sharing.models import Access, Export, ExportRecord, Record, Verdict
from sharing.selection import RecordSelection, iso_utc
from sharing.selectors.records import record_proof, records_to_check
from sharing.storage import envelope_storage, file_save
from sharing.verification.access import OwnerRead, accesses_open_for
from sharing.verification.check import Verification, records_verify
from sharing.verification.keys import RecordKeys
from sharing.verification.signature import signature_facts
from smcrypto import envelope as envelopes
from smcrypto import provenance, sm4
from smcrypto.errors import CryptoError
from smcrypto.sm3 import sm3_hasher, sm3_hex
from smcrypto.stream import SealedWriter

logger = logging.getLogger(__name__)

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)

# Why a record is left out of an export (its entry in `excluded`).
NOT_ANCHORED = "not_anchored_yet"
SIGNATURE_REFUSED = "signature_refused"
REASONS = {
    Verdict.Outcome.TAMPERED: "integrity_check_failed",
    Verdict.Outcome.NO_ACCESS: "access_denied",
    Verdict.Outcome.NOT_ANCHORED_YET: NOT_ANCHORED,
    Verdict.Outcome.SIGNATURE_REFUSED: SIGNATURE_REFUSED,
}


# The export's records, kept as each batch is written: one INSERT of plain columns, without the
# ORM's per-object work (core.rows).
_EXPORT_RECORDS = FixedInsert(ExportRecord)


class _SignerUnknown(Exception):
    """The robot's public key on record is not the key that signed the record."""


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
    """A file written as plaintext, stored sealed: the bytes are counted, and hashed (SM3) when
    `hashed` (the MCAP file's digest is in the bundle; the bundle's own is not kept: its
    bundle_sm3 is hashed by bundle_write), on their way into a SealedWriter
    (smcrypto/stream.py). `tell` is the plaintext's, as the MCAP writer asks for its offsets."""

    def __init__(self, target: IO[bytes], key: bytes, *, hashed: bool = True) -> None:
        self.sealed = SealedWriter(target, key)
        self._sm3 = sm3_hasher() if hashed else None

    def write(self, data: bytes) -> int:
        if self._sm3 is not None:
            self._sm3.update(data)
        return self.sealed.write(data)

    def tell(self) -> int:
        return self.sealed.written

    def flush(self) -> None:
        """Nothing to flush: a segment is sealed as soon as it is full."""

    def close(self) -> tuple[int, str | None]:
        """Seal the last segment; (plaintext size, its SM3 in hex when hashed)."""
        self.sealed.close()
        return self.sealed.written, None if self._sm3 is None else self._sm3.finalize().hex()


def _run(export: Export) -> None:
    selection = RecordSelection.from_json(export.selection)
    records = records_to_check(export_records(export.requester, selection))
    # Read before the records: a record uploaded meanwhile is past the streams' last, never a
    # gap inside them.
    streams = export_streams(export.requester, selection).as_json()
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
    mcap_name = f"{export_file_stem(export)}.mcap"
    with (
        tempfile.TemporaryFile() as mcap_file,
        tempfile.TemporaryFile() as bundle_file,
        tempfile.TemporaryFile(mode="w+", encoding="ascii") as entries,
    ):
        mcap = _SealedOutput(mcap_file, key)
        builder = McapBuilder(mcap)
        proofs = {"chain_id": chain_id, "contract": contract}
        with _Encoder() as encoder:
            # Batch k's messages and lines made (by the encoder's process) while batch k+1 is
            # checked here; then written, in order.
            waiting: _Encoding | None = None
            for batch in export_batches(records, settings.EXPORT_BATCH):
                prepared, inside = _batch_prepared(
                    export, batch, accesses, keys, proofs, excluded, exported
                )
                exported += len(prepared)
                processed += len(batch)
                encoding = _Encoding(encoder.submit(prepared), inside, processed, exported)
                if waiting is not None:
                    _written(export, waiting, builder, entries)
                waiting = encoding
            if waiting is not None:
                _written(export, waiting, builder, entries)
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
            "streams": streams,
        }
        bundle = _SealedOutput(bundle_file, key, hashed=False)
        bundle_write(head, lambda: _lines(entries), bundle)
        bundle_size, _ = bundle.close()
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


def _batch_prepared(
    export: Export,
    batch: list[Record],
    accesses: dict[int, int],
    keys: RecordKeys,
    proofs: dict[str, object],
    excluded: list[dict],
    exported: int,
) -> tuple[list["_ToWrite"], list[ExportRecord]]:
    """The batch checked (`_verified`) and each record that holds opened for the encoder,
    numbered on from `exported`; each record left out listed in `excluded`, with why."""
    prepared: list[_ToWrite] = []
    inside: list[ExportRecord] = []
    for record, checked, reason in _verified(batch, export.requester, accesses):
        if reason:
            excluded.append(_excluded(record, reason))
            continue
        try:
            prepared.append(_prepared(record, checked, keys, exported + len(prepared) + 1, proofs))
        except _SignerUnknown as exc:
            logger.warning("export %s: record %s left out: %s", export.pk, record.pk, exc)
            excluded.append(_excluded(record, SIGNATURE_REFUSED))
            continue
        except (SharingError, OwnerKey.DoesNotExist, CryptoError) as exc:
            logger.warning("export %s: record %s not opened: %s", export.pk, record.pk, exc)
            excluded.append(_excluded(record, "cannot_open"))
            continue
        inside.append(ExportRecord(export_id=export.pk, record_id=record.pk))
    return prepared, inside


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
            checked = records_verify(
                records=wanted,
                viewer_id=requester.pk,
                kind=Access.Kind.EXPORT,
                accesses=accesses,
            )
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


@dataclass(frozen=True)
class _ToWrite:
    """A verified record opened, its bundle entry but its message's binding: what the encoder
    needs to make its MCAP message and its bundle line (no database, no key)."""

    entry: dict[str, object]
    data_type: str
    plaintext: bytes
    captured_ns: int
    topic: str
    sequence: int


def _prepared(
    record: Record,
    checked: Verification,
    keys: RecordKeys,
    sequence: int,
    proofs: dict[str, object],
) -> _ToWrite:
    """The record opened (as the check opened it, a signed record's) and its entry but the
    message. The envelope is the one the check let through."""
    data = checked.envelope
    header, plaintext = checked.opened or envelopes.open(keys.of(record), data)
    signature = _signature(record, header)
    batched = envelopes.provenance_format(header) == "v2"
    entry = {
        **record_proof(record, **proofs),
        "robot": str(record.robot_id),
        "topic": record.topic,
        "type": record.data_type,
        "seq": record.seq,
        "captured_at": header["time"],
        "envelope": base64.b64encode(data).decode("ascii"),
        "signature": signature,
        # What the robot signed, so that anyone checks the signature and rebuilds the message.
        "plaintext": None if signature is None else base64.b64encode(plaintext).decode("ascii"),
        # Its number in its stream and its place in its upload batch, as its envelope states
        # them (the verifier counts by the envelope's, and checks these against it).
        "topic_seq": header.get("topic_seq"),
        "batch": {name: header[name] for name in envelopes.BATCH_FIELDS} if batched else None,
    }
    return _ToWrite(
        entry, header["type"], plaintext, _micros(record.captured_at) * 1000, record.topic, sequence
    )


def _encoded(items: list[_ToWrite]) -> list[tuple[_ToWrite, EncodedMessage, int, str]]:
    """Each record's ROS message (authros_verify.messages, the rules the verifier runs again),
    its log time and its bundle line."""
    made = []
    for item in items:
        message = message_encode(data_type=item.data_type, plaintext=item.plaintext)
        log_time = message_log_time(message, item.captured_ns)
        binding = {
            "topic": item.topic,
            "sequence": item.sequence,
            "log_time": log_time,
            "publish_time": log_time,
            "message_encoding": message.message_encoding,
            "schema": message.schema_name,
            "sm3": "0x" + sm3_hex(message.data),
        }
        line = bundle_entry_line({**item.entry, "mcap": binding})
        made.append((replace(item, entry={}, plaintext=b""), message, log_time, line))
    return made


class _Encoder:
    """Where the messages and lines of a batch are made: one forked process beside the
    exporter when the machine has cores to spare (it touches no database, key or file: it
    gets each record opened and hands back bytes), else in the exporter itself."""

    def __init__(self) -> None:
        self._pool = None
        if "fork" in multiprocessing.get_all_start_methods() and (os.cpu_count() or 1) > 1:
            try:
                self._pool = multiprocessing.get_context("fork").Pool(1)
            except (AssertionError, OSError) as exc:  # a daemonic process, or no process left
                logger.info("exports encoded in the exporter itself: %s", exc)

    def submit(self, items: list[_ToWrite]) -> Any:
        if self._pool is None:
            return _Made(_encoded(items))
        return self._pool.apply_async(_encoded, (items,))

    def __enter__(self) -> "_Encoder":
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()


@dataclass(frozen=True)
class _Made:
    """A batch encoded in the exporter itself, answered as the forked process's would be."""

    made: list

    def get(self) -> list:
        return self.made


@dataclass(frozen=True)
class _Encoding:
    """A batch handed to the encoder: its answer to come, and what to record once written."""

    answer: Any
    inside: list[ExportRecord]
    processed: int
    exported: int


def _written(export: Export, encoding: _Encoding, builder: McapBuilder, entries: IO[str]) -> None:
    """A batch's messages into the MCAP file and its lines into the spooled bundle, in order;
    its records kept as the export's, its progress shown."""
    for item, message, log_time, line in encoding.answer.get():
        builder.add(topic=item.topic, message=message, log_time=log_time, sequence=item.sequence)
        entries.write(line + "\n")
    _EXPORT_RECORDS.insert(encoding.inside)
    Export.objects.filter(pk=export.pk).update(
        processed=encoding.processed, exported=encoding.exported
    )


def _signature(record: Record, header: dict) -> dict[str, str] | None:
    """The record's signature facts (signature_facts) for its bundle entry, once the robot's
    public key on record is seen to be the signer's; None for an unsigned record."""
    signer = header.get("signer")
    public_key = record.robot.public_key
    if signer and (not public_key or provenance.key_hash(public_key) != signer):
        raise _SignerUnknown(f"the robot's public key is not the signer {signer}")
    return signature_facts(record, header)


def _excluded(record: Record, reason: str) -> dict[str, object]:
    """A record left out, and why; its signer and topic_seq (the portal's word, from its row)
    so that the verifier names the gap it leaves `excluded` rather than `missing`."""
    return {
        "record": str(record.pk),
        "topic": record.topic,
        "captured_at": iso_utc(record.captured_at),
        "reason": reason,
        "signer": record.signer or None,
        "topic_seq": record.topic_seq,
    }


def _finish(export: Export, *, status: str, **fields: object) -> None:
    Export.objects.filter(pk=export.pk).update(status=status, finished_at=timezone.now(), **fields)


def _micros(moment: datetime) -> int:
    delta = moment - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
