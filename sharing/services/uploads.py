"""Uploads: a robot's envelopes checked, stored durably, and their anchoring queued.

An upload is all or none and committed (the files made durable, then the rows) before it is
acknowledged. Each envelope must parse, name its robot and owner, open under one of the owner's
keys, carry the robot's signature if the robot is paired, and a sequence number above every
earlier one of the robot; a refusal that may be an attack is a SecurityEvent. Anchoring
(sharing/services/anchoring.py) is queued on commit and retried by the sweep (sweep.py).

A paired robot signs each upload batch once (DESIGN.md "Provenance v2"; v1, one signature per
envelope, from older agents): the signatures of an upload are verified together, each distinct
one once (provenance.claims_hold), so a batch costs one SM2 verification. Each v2 record's
`topic_seq` is stored, once ever per (signer, topic): a number used again, by a record stored
before (a tombstone too) or twice in one upload, refuses the whole upload.
"""

import logging
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any, NoReturn

from django.conf import settings
from django.core.exceptions import ImproperlyConfigured
from django.db import IntegrityError, connections, models, router, transaction
from django.db.models import Q
from django.utils import timezone
from redis.exceptions import RedisError

from accounts.identity import owner_identity_check
from accounts.models import ChainState, OwnerKey, Robot
from accounts.selectors import owner_key_bytes, owner_keys
from core.commits import commits_durable
from core.redis_client import get_redis
from core.rows import FixedUpdate
from sharing.cache import envelope_cache_put_queued
from sharing.disk import disk_room_check
from sharing.errors import (
    EnvelopeTooLarge,
    ForgedEnvelope,
    HeaderMismatch,
    InvalidEnvelope,
    ReplayedSequence,
    SequenceConflict,
    SignatureRefused,
    StorageUnavailable,
    TopicSeqReused,
    UnknownKey,
)
from sharing.models import Record, SecurityEvent
from sharing.services.anchoring import anchor_schedule_queued
from sharing.storage import EnvelopeWriter, envelope_storage
from smcrypto import CryptoError, envelope, provenance, sm3
from smcrypto.errors import SignatureInvalid, SignerMismatch
from smcrypto.merkle import MerkleTree

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

# An envelope sealed under a key retired less than this long ago is still accepted from a robot
# whose key file is updated by hand (a paired robot fetches the new key and re-seals). One
# captured before the key was retired always is, from any robot (a spool filled while the robot
# was offline), give or take settings.KEY_ROTATION_CLOCK_SKEW seconds of robot clock.
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
    digest: str  # SM3 of data, hex
    signer: str  # the robot key that signed it (hex), or "" (a robot added by hand)
    # The robot's signature left to verify (with the others of the upload), None if unsigned;
    # _PENDING for a v2 record until its batch is seen whole (_batch_claims).
    claim: provenance.SignatureClaim | None
    topic_seq: int | None  # a v2 record's place in its signer's count of the topic
    plaintext: bytes = b""  # kept for a v2 record until its claim is made


def record_create(*, robot: Robot, data: bytes) -> Record:
    """Store one envelope uploaded by `robot`; see `record_create_batch`."""
    return record_create_batch(robot=robot, envelopes=[data])[0]


# An upload's two writes, their SQL written once (core/rows.py): the robot's last seq moved on
# only if every seq of the upload is above it, and the new records.
_ROBOT_SEQ_MOVE = FixedUpdate(
    Robot,
    columns=("last_seq", "last_upload_at"),
    where="id = %s AND last_seq < %s",
    params_of=("id", "last_seq"),
)


class _UploadRows:
    """An upload's Record rows INSERTed by one prepared statement run for each row
    (executemany of tuples): the columns every record of an upload shares (its owner and
    robot, the defaults, created_at) prepared once per upload by their fields, the ones of
    each record's own as their fields would prepare them: text and integers as they are (the
    exact CharField and integer classes hand them on unchanged), the id and capture time
    through their fields."""

    # Each record's own columns, from its _CheckedUpload (and its file's name).
    OWN = (
        "id",
        "topic",
        "data_type",
        "seq",
        "captured_at",
        "key_id",
        "digest",
        "signer",
        "topic_seq",
        "size",
        "storage_name",
    )
    _AS_IS = (models.CharField, models.BigIntegerField, models.PositiveIntegerField)

    def __init__(self) -> None:
        self._fields = list(Record._meta.concrete_fields)
        names = [field.attname for field in self._fields]
        unknown = set(self.OWN) - set(names)
        if unknown:
            raise ImproperlyConfigured(f"Record has no column(s) {sorted(unknown)}")
        self._own = {field.attname: field for field in self._fields if field.attname in self.OWN}
        self._sql: dict[str, str] = {}

    def insert(
        self, robot: Robot, checked: Sequence[_CheckedUpload], names: Sequence[str]
    ) -> list[Record]:
        alias = router.db_for_write(Record)
        connection = connections[alias]
        # The shared columns, their values and as prepared, once: the new record's
        # defaults, its owner and robot, and created_at (pre_save: one moment an upload).
        template = Record(owner_id=robot.owner_id, robot_id=robot.pk)
        shared = {}
        for field in self._fields:
            if field.attname not in self._own:
                value = field.pre_save(template, True)
                shared[field.attname] = (value, field.get_db_prep_save(value, connection))
        prepare = [self._preparer(field, connection) for field in self._fields]
        records, rows = [], []
        for upload, name in zip(checked, names, strict=True):
            own = {
                "id": upload.record_id,
                "topic": upload.header["topic"],
                "data_type": upload.header["type"],
                "seq": upload.header["seq"],
                "captured_at": upload.captured_at,
                "key_id": upload.key.key_id,
                "digest": upload.digest,
                "signer": upload.signer,
                "topic_seq": upload.topic_seq,
                "size": len(upload.data),
                "storage_name": name,
            }
            values, row = [], []
            for field, own_prepared in zip(self._fields, prepare, strict=True):
                if own_prepared is None:
                    value, prepared = shared[field.attname]
                else:
                    value = own[field.attname]
                    prepared = own_prepared(value)
                values.append(value)
                row.append(prepared)
            # Positional, in the order of the concrete fields, as Model.from_db builds one.
            record = Record(*values)
            Record.robot.field.set_cached_value(record, robot)
            records.append(record)
            rows.append(row)
        sql = self._sql.get(alias)
        if sql is None:
            sql = self._sql[alias] = self._build(connection)
        with connection.cursor() as cursor:
            cursor.executemany(sql, rows)
        for record in records:
            record._state.adding = False
            record._state.db = alias
        return records

    def _preparer(self, field: models.Field, connection: Any) -> Callable[[object], object] | None:
        """How one record's own value of `field` reaches the database; None if shared."""
        if field.attname not in self._own:
            return None
        if type(field) in self._AS_IS:
            integer = field.get_internal_type() if type(field) is not models.CharField else None

            def as_is(value: object) -> object:
                kind = type(value)
                if kind is str and integer is None:
                    return value
                if kind is int and integer is not None:
                    return connection.ops.adapt_integerfield_value(value, integer)
                return field.get_db_prep_save(value, connection)

            return as_is
        return lambda value: field.get_db_prep_save(value, connection)

    def _build(self, connection: Any) -> str:
        quote = connection.ops.quote_name
        columns = ", ".join(quote(field.column) for field in self._fields)
        values = ", ".join(["%s"] * len(self._fields))
        return f"INSERT INTO {quote(Record._meta.db_table)} ({columns}) VALUES ({values})"  # noqa: S608


_RECORD_ROWS = _UploadRows()


def record_create_batch(*, robot: Robot, envelopes: Sequence[bytes]) -> list[Record]:
    """Store envelopes uploaded by `robot`, all or none, and queue their anchoring.

    Each must parse, name this robot and its owner, be sealed under the owner's current key
    (or one retired after the envelope's capture time, or, for a robot not paired, within
    KEY_ROTATION_GRACE) with a valid tag, and carry a sequence number above every earlier one
    of this robot. A paired robot's must hold its signature (v1, or v2: each record folding
    to its batch's signed root), every signature verified once; a v2 record's `topic_seq`
    must be unused for its signer and topic, in the database and in the upload (409
    TopicSeqReused and a SecurityEvent). An exact resend of stored envelopes is answered
    ReplayedSequence first, as before there were topic_seqs: the agent counts it delivered.
    """
    if not envelopes:
        raise InvalidEnvelope("no envelopes in the upload")
    owner_keys_read = owner_keys(robot.owner)  # read once, for the check and the unsealing
    # The owner's commitment on chain must be the key the envelopes are sealed under.
    owner_identity_check(owner=robot.owner, keys=owner_keys_read)
    keys = _UploadKeys(owner_keys_read, robot)
    disk_room_check(sum(len(data) for data in envelopes))
    # The files first, durable before the transaction starts: the robot's row lock (and
    # SQLite's write lock) is then held for the rows alone, not for a disk sync. They are
    # written as the envelopes pass their checks (a writer thread beside the checks), made
    # durable once all are checked; those of an upload refused or failed are removed again.
    files = EnvelopeWriter(envelope_storage())
    try:
        checked = []
        for data in envelopes:
            upload = _check_upload(robot, data, keys)
            checked.append(upload)
            files.add(f"{robot.owner_id}/{upload.record_id}.env", upload.data)
        checked = _batch_claims(robot, checked)
        seqs = [c.header["seq"] for c in checked]
        if seqs != sorted(set(seqs)):
            raise InvalidEnvelope("sequence numbers in one upload must strictly increase")
        _signatures_hold(robot, checked)
        _topic_seqs_distinct(robot, checked)
        names = files.durable()
    except BaseException:
        files.discard()  # refused (each refusal raised its own alarm) or failed
        raise
    try:
        try:
            records = _records_insert(robot, checked, seqs, names)
        except IntegrityError:
            # Another upload stored one of these numbers between this one's checks and its
            # insert (two uploads at once): answered as if it had been stored first.
            _stored_conflict_check(robot, checked)
            raise
    except BaseException as refused:
        # Nothing of a refused or failed upload stays behind, not even its files.
        files.discard()
        if isinstance(refused, SequenceConflict):
            _sequence_conflict_alarm(robot, refused.detail)  # outside the refused transaction
        elif isinstance(refused, TopicSeqReused):
            _topic_seq_reused_alarm(robot, refused.detail)
        raise
    # The robot drops its copies once answered: the rows must outlive a power loss too. (Not
    # in the block above: the rows are committed, so their files stay whatever happens here;
    # a robot told to send again is answered replayed_sequence, which it counts delivered.)
    try:
        commits_durable()
    except OSError as exc:
        logger.error("an upload's rows could not be made durable: %s", exc)
        raise StorageUnavailable(
            "the portal could not make the upload durable; send it again"
        ) from exc
    return records


def _records_insert(
    robot: Robot, checked: Sequence[_CheckedUpload], seqs: Sequence[int], names: Sequence[str]
) -> list[Record]:
    """The upload's rows, in one transaction: the robot's last seq moved on (the sequence
    check, and the robot's row lock), then its topic_seqs checked against those stored (under
    that lock, so an upload of the same robot committed meanwhile is seen), then the records."""
    with transaction.atomic():
        # Moving the robot's last seq on is the check and the row lock in one statement:
        # it only moves when every seq of the upload is above it. An exact resend is answered
        # here (replayed_sequence), before its topic_seqs, which are its own, are looked at.
        moved = _ROBOT_SEQ_MOVE.run((seqs[-1], timezone.now()), (robot.pk, seqs[0]))
        if not moved:
            last_seq = Robot.objects.values_list("last_seq", flat=True).get(pk=robot.pk)
            _sequence_check(robot, checked, last_seq=last_seq)
        _topic_seqs_unused(robot, checked)
        records = _RECORD_ROWS.insert(robot, checked, names)
        transaction.on_commit(lambda: _after_upload(robot.owner_id, checked))
    return records


def _topic_seqs_distinct(robot: Robot, checked: Sequence[_CheckedUpload]) -> None:
    """TopicSeqReused if two records of the upload hold one place of one topic's count."""
    seen: set[tuple[str, int]] = set()
    for upload in checked:
        if upload.topic_seq is None:
            continue
        place = (upload.header["topic"], upload.topic_seq)
        if place in seen:
            detail = _topic_seq_detail(robot, upload, within_upload=True)
            _topic_seq_reused_alarm(robot, detail)
            raise TopicSeqReused(
                f"topic_seq {upload.topic_seq} of {upload.header['topic']} is in this upload "
                "twice: each number of a topic is used once",
                detail=detail,
            )
        seen.add(place)


def _topic_seqs_unused(robot: Robot, checked: Sequence[_CheckedUpload]) -> None:
    """TopicSeqReused if a record of the upload takes a place of its topic's count that a
    record stored before holds (deleted or not: a tombstone keeps its number)."""
    wanted = {
        (upload.header["topic"], upload.topic_seq): upload
        for upload in checked
        if upload.topic_seq is not None
    }
    if not wanted:
        return
    by_topic: dict[str, list[int]] = {}
    for topic, topic_seq in wanted:
        by_topic.setdefault(topic, []).append(topic_seq)
    # One range of the (signer, topic, topic_seq) index per topic of the upload.
    places = Q()
    for topic, topic_seqs in by_topic.items():
        places |= Q(topic=topic, topic_seq__in=topic_seqs)
    stored = (
        Record.objects.filter(signer=robot.key_hash)
        .filter(places)
        .values_list("topic", "topic_seq")
    )
    for place in stored:
        if place in wanted:
            upload = wanted[place]
            raise TopicSeqReused(
                f"topic_seq {upload.topic_seq} of {upload.header['topic']} is stored already "
                "with another record: a number of a topic is used once, ever (a robot that "
                "lost its counter, or its key in other hands)",
                detail=_topic_seq_detail(robot, upload, within_upload=False),
            )


def _stored_conflict_check(robot: Robot, checked: Sequence[_CheckedUpload]) -> None:
    """After the database refused the upload's rows (a unique constraint): raise what the
    upload would have been answered had the other upload been stored first, if that is it."""
    last_seq = Robot.objects.values_list("last_seq", flat=True).get(pk=robot.pk)
    if last_seq >= checked[0].header["seq"]:
        _sequence_check(robot, checked, last_seq=last_seq)
    _topic_seqs_unused(robot, checked)


def _topic_seq_detail(robot: Robot, upload: _CheckedUpload, *, within_upload: bool) -> dict:
    return {
        "robot": str(robot.id),
        "signer": upload.signer,
        "topic": upload.header["topic"],
        "topic_seq": upload.topic_seq,
        "seq": upload.header["seq"],
        "within_upload": within_upload,
    }


def _topic_seq_reused_alarm(robot: Robot, detail: dict) -> None:
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.TOPIC_SEQ_REUSED, owner=robot.owner, detail=detail
    )
    security_log.warning(
        "robot %s uploaded topic_seq %s of %s, a number used already",
        detail["robot"],
        detail["topic_seq"],
        detail["topic"],
    )


def _sequence_check(robot: Robot, checked: Sequence[_CheckedUpload], *, last_seq: int) -> NoReturn:
    """An upload whose first seq is not above the robot's last: ReplayedSequence if these very
    envelopes are stored (the agent counts them delivered), else SequenceConflict and a
    SecurityEvent (the agent keeps them as refused, and the owner is told)."""
    stored = dict(
        Record.objects.filter(robot=robot, seq__in=[c.header["seq"] for c in checked]).values_list(
            "seq", "digest"
        )
    )
    if all(stored.get(c.header["seq"]) == c.digest for c in checked):
        raise ReplayedSequence(f"seq {checked[0].header['seq']} is stored already, as sent")
    seq = checked[0].header["seq"]
    raise SequenceConflict(
        f"seq {seq} is not above {last_seq}, the last one of this robot, and is not data this "
        "robot uploaded: check the robot, and revoke its token if it is not in your hands",
        detail={"robot": str(robot.id), "seq": seq, "last_seq": last_seq},
    )


def _sequence_conflict_alarm(robot: Robot, detail: dict) -> None:
    SecurityEvent.objects.create(
        kind=SecurityEvent.Kind.SEQUENCE_CONFLICT, owner=robot.owner, detail=detail
    )
    security_log.warning(
        "robot %s uploaded seq %s, not above its last %s, with other data than it stored",
        detail["robot"],
        detail["seq"],
        detail["last_seq"],
    )


def _after_upload(owner_id: int, uploads: Sequence[_CheckedUpload]) -> None:
    """Cache the envelopes and queue the owner's anchoring, in one round trip to Redis."""
    items = [(upload.record_id, upload.data) for upload in uploads]
    with get_redis().pipeline(transaction=False) as pipe:
        finishers = [
            finish
            for finish in (
                envelope_cache_put_queued(pipe, items),
                anchor_schedule_queued(pipe, owner_id=owner_id),
            )
            if finish is not None
        ]
        try:
            answers = pipe.execute(raise_on_error=False)
        except RedisError as exc:  # Redis unreachable: each says what that means for it
            answers = [exc] * len(finishers)
    for finish, answer in zip(finishers, answers, strict=True):
        finish(answer)


class _UploadKeys:
    """The owner's keys an upload may be sealed under, each unwrapped once per upload: the
    current key, one retired after the envelope's capture (give or take
    settings.KEY_ROTATION_CLOCK_SKEW), or, for a robot not paired, one retired within
    KEY_ROTATION_GRACE (a paired robot fetches the new key and re-seals)."""

    def __init__(self, keys: Sequence[OwnerKey], robot: Robot) -> None:
        self._keys = {key.key_id: key for key in keys}
        self._unwrapped: dict[str, bytes] = {}
        self._grace_start = None if robot.public_key else timezone.now() - KEY_ROTATION_GRACE
        self._skew = timedelta(seconds=settings.KEY_ROTATION_CLOCK_SKEW)

    def get(self, key_id: str, captured_at: datetime) -> tuple[OwnerKey, bytes] | None:
        """The key `key_id` and its bytes, or None if an envelope captured at `captured_at` may
        not be sealed under it."""
        key = self._keys.get(key_id)
        if key is None or not self._usable(key, captured_at):
            return None
        if key_id not in self._unwrapped:
            self._unwrapped[key_id] = owner_key_bytes(key)
        return key, self._unwrapped[key_id]

    def _usable(self, key: OwnerKey, captured_at: datetime) -> bool:
        if key.is_current:
            return True
        if key.retired_at is None:
            return False
        if self._grace_start is not None and key.retired_at > self._grace_start:
            return True
        return captured_at <= key.retired_at + self._skew


def _check_upload(robot: Robot, data: bytes, keys: _UploadKeys) -> _CheckedUpload:
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
    captured_at = datetime.fromisoformat(header["time"].replace("Z", "+00:00"))
    usable = keys.get(info.key_id.hex(), captured_at)
    if usable is None:
        raise UnknownKey("the envelope is not sealed under the owner's current key")
    key, key_bytes = usable
    try:
        _sealed_header, plaintext = envelope.open(key_bytes, data, info=info)
    except CryptoError:
        SecurityEvent.objects.create(
            kind=SecurityEvent.Kind.FORGED_UPLOAD,
            owner=owner,
            detail={"robot": str(robot.id), "seq": header["seq"], "topic": header["topic"]},
        )
        security_log.warning("forged upload refused: robot %s seq %s", robot.id, header["seq"])
        raise ForgedEnvelope("the envelope does not open under the owner's key") from None
    if captured_at < EPOCH:
        # The chain stores capture times as unsigned microseconds since 1970.
        raise InvalidEnvelope("the capture time must be 1970-01-01T00:00:00Z or later")
    v2 = envelope.provenance_format(header) == "v2"
    signer, claim = _signature_claim(robot, header, plaintext, deferred=v2)
    data = bytes(data)
    return _CheckedUpload(
        uuid.uuid4(),
        data,
        header,
        key,
        captured_at,
        sm3.sm3_hex(data),
        signer,
        claim,
        header["topic_seq"] if v2 else None,
        bytes(plaintext) if claim is _PENDING else b"",
    )


def _signature_claim(
    robot: Robot, header: dict, plaintext: bytes, *, deferred: bool = False
) -> tuple[str, provenance.SignatureClaim | None]:
    """The robot key that signed the envelope (DESIGN.md "Provenance", v1 or v2 as its header
    says) and its signature left to verify (`_signatures_hold`), or ("", None) for a robot
    added by hand that signs nothing. A paired robot's envelope must carry `signer` and `sig`
    and name the robot's own key; a v2 one must fold up its batch path to a root its signature
    can be over; a robot added by hand has no key, so an envelope of its naming one is refused
    too. Each refusal is a SecurityEvent. With `deferred` (a v2 record), the claim is
    _PENDING once the signer holds: _batch_claims makes it with the rest of its batch."""
    signed = "signer" in header or "sig" in header
    if not robot.key_hash and not signed:
        return "", None
    if not signed:
        _signature_refused(robot, header, SecurityEvent.Kind.UNSIGNED_UPLOAD)
        raise SignatureRefused(
            "the envelope carries no robot signature (signer, sig): a paired robot signs every "
            "envelope with its pairing key"
        )
    if not robot.key_hash or header.get("signer") != robot.key_hash:
        _signature_refused(robot, header, SecurityEvent.Kind.FOREIGN_SIGNER)
        raise SignatureRefused("the envelope is signed by a key that is not this robot's")
    if robot.key_chain_state == ChainState.FAILED:
        # Its records could never be anchored as genuine (another account registered the key
        # first, or it was revoked before): refused rather than kept waiting for good.
        raise SignatureRefused(
            "this robot's key could not be registered on chain for its owner: pair the robot "
            "again (a new key)"
        )
    if deferred:
        return robot.key_hash, _PENDING
    return robot.key_hash, _claim_made(robot, header, plaintext)


def _claim_made(robot: Robot, header: dict, plaintext: bytes) -> provenance.SignatureClaim:
    """provenance.signature_claim of one record, its refusals SecurityEvents."""
    try:
        return provenance.signature_claim(robot.public_key, header, plaintext)
    except SignerMismatch:
        _signature_refused(robot, header, SecurityEvent.Kind.FOREIGN_SIGNER)
        raise SignatureRefused("the envelope is signed by a key that is not this robot's") from None
    except SignatureInvalid as exc:
        _signature_refused(robot, header, SecurityEvent.Kind.BAD_SIGNATURE, reason=str(exc))
        raise SignatureRefused(
            f"the envelope's robot signature cannot hold: {exc}; nothing of the upload is stored"
        ) from None


# A v2 record's claim before its batch is seen whole.
_PENDING = provenance.SignatureClaim(public_key="", message=b"", sig="")


def _batch_claims(robot: Robot, checked: list[_CheckedUpload]) -> list[_CheckedUpload]:
    """The v2 records' claims, each batch's tree built once: a batch whose records are all in
    the upload, each at its own sig_index, has its tree built from their leaves, and each
    record whose sig_path is that tree's path of its index folds to the tree's root (the same
    claim for all: one record's made by provenance.signature_claim, with every check of its
    signer and shape). Any other v2 record (a path not the tree's, a batch not whole) has its
    own claim folded up its own path, as provenance.signature_claim makes it."""
    batches: dict[tuple[str, int], dict[int, int]] = {}
    for place, upload in enumerate(checked):
        if upload.claim is _PENDING:
            by_index = batches.setdefault((upload.header["sig"], upload.header["sig_size"]), {})
            by_index.setdefault(upload.header["sig_index"], place)
    claims: dict[int, provenance.SignatureClaim] = {}
    for (_sig, size), by_index in batches.items():
        if len(by_index) != size:
            continue  # not whole here (or an index twice): each record folds its own path
        places = [by_index[index] for index in range(size)]
        try:
            tree = MerkleTree(
                [provenance.batch_leaf(checked[at].header, checked[at].plaintext) for at in places]
            )
        except SignatureInvalid:
            continue  # refused below, by the record's own claim
        claim = None
        for index, at in enumerate(places):
            if checked[at].header["sig_path"] != b"".join(tree.path(index)).hex():
                continue
            if claim is None:
                upload = checked[at]
                claim = _claim_made(robot, upload.header, upload.plaintext)
            claims[at] = claim
    return [
        upload
        if upload.claim is not _PENDING
        else replace(
            upload,
            claim=claims.get(place) or _claim_made(robot, upload.header, upload.plaintext),
            plaintext=b"",
        )
        for place, upload in enumerate(checked)
    ]


def _signatures_hold(robot: Robot, checked: Sequence[_CheckedUpload]) -> None:
    """Verify the upload's robot signatures together, each distinct one once (the records of
    one v2 batch make one: one SM2 verification a batch). One that does not hold refuses the
    whole upload, with a SecurityEvent naming the first record it refuses: its content, its
    place in the batch (sig_index, sig_size, sig_path) or the batch's signature is not what
    the robot signed."""
    signed = [upload for upload in checked if upload.claim is not None]
    if not signed:
        return
    holds = provenance.claims_hold([upload.claim for upload in signed])
    refused = [upload for upload, held in zip(signed, holds, strict=True) if not held]
    if not refused:
        return
    first = refused[0]
    _signature_refused(robot, first.header, SecurityEvent.Kind.BAD_SIGNATURE, refused=len(refused))
    raise SignatureRefused(
        f"the robot signature of {len(refused)} of the {len(checked)} envelopes does not match "
        f"their content or their place in their batch (first: seq {first.header['seq']}); "
        "nothing of the upload is stored"
    )


def _signature_refused(robot: Robot, header: dict, kind: str, **more: object) -> None:
    detail = {"robot": str(robot.id), "seq": header["seq"], "topic": header["topic"], **more}
    if isinstance(header.get("signer"), str):
        detail["signer"] = header["signer"][:64]
    if envelope.provenance_format(header) == "v2":
        detail.update(sig_index=header["sig_index"], sig_size=header["sig_size"])
    SecurityEvent.objects.create(kind=kind, owner=robot.owner, detail=detail)
    security_log.warning("upload refused (%s): robot %s seq %s", kind, robot.id, header["seq"])
