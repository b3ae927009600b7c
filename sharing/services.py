"""Actions on records and grants: uploads, grants and revocations, and their sweep.

Uploads are committed (row and durable envelope) before they are acknowledged; anchoring
(sharing/anchoring.py) is queued on commit and retried by the sweep. A grant takes effect
once `authorityGrant` is confirmed on chain (`grant_sync_on_chain`, run by the worker); a
revocation is refused by the portal at once and `authorityRevoke` follows.
"""

import dataclasses
import logging
import uuid
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import NoReturn

from django.conf import settings
from django.db import IntegrityError, transaction
from django.utils import timezone
from redis.exceptions import RedisError

from accounts.identity import owner_identity_check
from accounts.models import ChainActivity, ChainState, Owner, OwnerKey, OwnerToken, Robot
from accounts.selectors import (
    owner_by_identifier,
    owner_eoa_account,
    owner_key_bytes,
    owner_keys,
)
from accounts.services.activity import chain_activity_record
from alerts.services import grant_received_alert, grant_revoked_alert
from chainworker.codec import TxResult
from chainworker.errors import InsufficientFunds, TransactionReverted
from chainworker.services import chain_client, chain_work_check
from chainworker.work import WAITING_FOR_GAS, ChainWorkNotReady, exclusive
from core.commits import commits_durable
from core.outbox import enqueue
from core.redis_client import get_redis
from core.rows import FixedInsert, FixedUpdate
from sharing.anchoring import anchor_schedule, anchor_schedule_queued
from sharing.cache import envelope_cache_put_queued
from sharing.disk import disk_room_check
from sharing.errors import (
    AlreadyGranted,
    EnvelopeTooLarge,
    ForgedEnvelope,
    GranteeNotRegistered,
    HeaderMismatch,
    InvalidEnvelope,
    InvalidGrantTerms,
    NoGrant,
    NotRegisteredYet,
    OwnerNotFound,
    ReplayedSequence,
    RevocationPending,
    SelfGrant,
    SequenceConflict,
    SignatureRefused,
    StorageUnavailable,
    TokenCannotWiden,
    UnknownKey,
)
from sharing.models import Grant, GrantChange, Record, SecurityEvent
from sharing.scope import (
    ALL_RECORDS_COMMITMENT,
    ScopeError,
    expiry_seconds,
    scope_commitment,
    scope_make,
)
from sharing.selection import RecordSelection, iso_utc
from sharing.selectors import grant_list_changed_with, grant_list_made_with
from sharing.storage import envelope_storage, envelopes_save
from smcrypto import CryptoError, envelope, provenance, sm3

logger = logging.getLogger(__name__)
# Withdraws the exports whose requester may no longer view every record in them.
EXPORTS_RECHECK_TASK = "sharing.tasks.exports_recheck"
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
_RECORD_INSERT = FixedInsert(Record)


def record_create_batch(*, robot: Robot, envelopes: Sequence[bytes]) -> list[Record]:
    """Store envelopes uploaded by `robot`, all or none, and queue their anchoring.

    Each must parse, name this robot and its owner, be sealed under the owner's current key
    (or one retired after the envelope's capture time, or, for a robot not paired, within
    KEY_ROTATION_GRACE) with a valid tag, and carry a sequence number above every earlier one
    of this robot.
    """
    if not envelopes:
        raise InvalidEnvelope("no envelopes in the upload")
    owner_keys_read = owner_keys(robot.owner)  # read once, for the check and the unsealing
    # The owner's commitment on chain must be the key the envelopes are sealed under.
    owner_identity_check(owner=robot.owner, keys=owner_keys_read)
    keys = _UploadKeys(owner_keys_read, robot)
    checked = [_check_upload(robot, data, keys) for data in envelopes]
    seqs = [c.header["seq"] for c in checked]
    if seqs != sorted(set(seqs)):
        raise InvalidEnvelope("sequence numbers in one upload must strictly increase")
    disk_room_check(sum(len(upload.data) for upload in checked))
    # The files first, durable before the transaction starts: the robot's row lock (and
    # SQLite's write lock) is then held for the rows alone, not for a disk sync. Files of an
    # upload refused or failed below are removed again.
    names = envelopes_save(
        envelope_storage(), [(f"{robot.owner_id}/{c.record_id}.env", c.data) for c in checked]
    )
    try:
        with transaction.atomic():
            # Moving the robot's last seq on is the check and the row lock in one statement:
            # it only moves when every seq of the upload is above it.
            moved = _ROBOT_SEQ_MOVE.run((seqs[-1], timezone.now()), (robot.pk, seqs[0]))
            if not moved:
                last_seq = Robot.objects.values_list("last_seq", flat=True).get(pk=robot.pk)
                _sequence_check(robot, checked, last_seq=last_seq)
            records = [
                Record(
                    id=upload.record_id,
                    owner_id=robot.owner_id,
                    robot=robot,
                    topic=upload.header["topic"],
                    data_type=upload.header["type"],
                    seq=upload.header["seq"],
                    captured_at=upload.captured_at,
                    key_id=upload.key.key_id,
                    digest=upload.digest,
                    signer=upload.signer,
                    size=len(upload.data),
                    storage_name=name,
                )
                for upload, name in zip(checked, names, strict=True)
            ]
            _RECORD_INSERT.insert(records)
            transaction.on_commit(lambda: _after_upload(robot.owner_id, checked))
    except BaseException as refused:
        # Nothing of a refused or failed upload stays behind, not even its files.
        _files_forget(names)
        if isinstance(refused, SequenceConflict):
            _sequence_conflict_alarm(robot, refused.detail)  # outside the refused transaction
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


def _files_forget(names: Sequence[str]) -> None:
    storage = envelope_storage()
    for name in names:
        with suppress(OSError):
            storage.delete(name)


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
        _sealed_header, plaintext = envelope.open(key_bytes, data)
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
    signer = _signature_check(robot, header, plaintext)
    data = bytes(data)
    return _CheckedUpload(uuid.uuid4(), data, header, key, captured_at, sm3.sm3_hex(data), signer)


def _signature_check(robot: Robot, header: dict, plaintext: bytes) -> str:
    """The robot key that signed the envelope (DESIGN.md "Provenance"), "" for a robot added by
    hand that signs nothing. A paired robot's envelope must carry `signer` and `sig`, name the
    robot's own key, and its signature must hold over the plaintext; a robot added by hand has
    no key, so an envelope of its naming one is refused too. Each refusal is a SecurityEvent."""
    signed = "signer" in header or "sig" in header
    if not robot.key_hash and not signed:
        return ""
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
    if not provenance.verify_header(robot.public_key, header, plaintext):
        _signature_refused(robot, header, SecurityEvent.Kind.BAD_SIGNATURE)
        raise SignatureRefused("the envelope's robot signature does not match its content")
    return robot.key_hash


def _signature_refused(robot: Robot, header: dict, kind: str) -> None:
    detail = {"robot": str(robot.id), "seq": header["seq"], "topic": header["topic"]}
    if isinstance(header.get("signer"), str):
        detail["signer"] = header["signer"][:64]
    SecurityEvent.objects.create(kind=kind, owner=robot.owner, detail=detail)
    security_log.warning("upload refused (%s): robot %s seq %s", kind, robot.id, header["seq"])


# --- grants ----------------------------------------------------------------------------------


def owner_resolve(identifier: str) -> Owner:
    """An owner named by username or by EOA address; OwnerNotFound for anything else."""
    owner = owner_by_identifier(identifier)
    if owner is None:
        raise OwnerNotFound(
            f"There is no owner with the username or address “{identifier.strip()}”: check the "
            "spelling, or ask them for their username."
        )
    return owner


@dataclass(frozen=True)
class GrantTerms:
    """What a grant covers and until when: its scope (all records by default) and expiry."""

    scope: RecordSelection = dataclasses.field(default_factory=RecordSelection)
    expires_at: datetime | None = None

    @classmethod
    def of(cls, grant: Grant) -> "GrantTerms":
        return cls(scope=grant.scope, expires_at=grant.expires_at)

    def within(self, other: "GrantTerms") -> bool:
        """Whether these terms give no more than `other`: a scope inside its scope, and an
        expiry no later (never expiring is the latest)."""
        if other.expires_at is not None and (
            self.expires_at is None or self.expires_at > other.expires_at
        ):
            return False
        return self.scope.within(other.scope)

    def as_json(self) -> dict[str, object]:
        """The terms as a GrantChange keeps them: the scope's JSON and the expiry."""
        return {**self.scope.as_json(), "expires_at": iso_utc(self.expires_at)}

    @classmethod
    def from_json(cls, value: dict) -> "GrantTerms":
        expiry = value.get("expires_at")
        return cls(
            scope=RecordSelection.from_json(value),
            expires_at=datetime.fromisoformat(expiry) if expiry else None,
        )


ALL_RECORDS_FOREVER = GrantTerms()
# An expiry this close to now could pass before the grant is confirmed on chain.
MIN_GRANT_LIFETIME = timedelta(minutes=5)


def grant_terms_make(
    *,
    owner: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
    expires_at: datetime | None = None,
) -> GrantTerms:
    """The terms of a grant of `owner`'s, checked: robots must be the owner's, the window
    ordered, the expiry at least MIN_GRANT_LIFETIME ahead. InvalidGrantTerms says what is
    wrong, in words for the owner."""
    try:
        scope = scope_make(robots=robots, topics=topics, since=since, until=until)
    except ScopeError as exc:
        raise InvalidGrantTerms(_sentence(str(exc))) from None
    if scope.robots:
        own = set(
            Robot.objects.filter(owner=owner, pk__in=scope.robots).values_list("pk", flat=True)
        )
        if len(own) != len(scope.robots):
            raise InvalidGrantTerms("A grant can only name your own robots.")
    if expires_at is not None:
        if expires_at.tzinfo is None:
            raise InvalidGrantTerms("The expiry needs a time zone.")
        expires_at = expires_at.astimezone(UTC).replace(microsecond=0)  # whole seconds on chain
        if expires_at < timezone.now() + MIN_GRANT_LIFETIME:
            raise InvalidGrantTerms(
                "The expiry must be at least "
                f"{int(MIN_GRANT_LIFETIME.total_seconds() // 60)} minutes in the future."
            )
        if expiry_seconds(expires_at) >= 2**64:
            raise InvalidGrantTerms("The expiry is too far in the future.")
    return GrantTerms(scope=scope, expires_at=expires_at)


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def _terms_fields(terms: GrantTerms) -> dict[str, object]:
    scope = terms.scope
    return {
        "scope_robots": [str(robot) for robot in scope.robots],
        "scope_topics": list(scope.topics),
        "scope_since": scope.since,
        "scope_until": scope.until,
        "expires_at": terms.expires_at,
    }


_ALREADY_GRANTED = (
    "{grantee} already has access. To change which records they may read, change that grant "
    "instead."
)
_REVOCATION_PENDING = (
    "{grantee} no longer has access, but the revocation is still on its way to the chain. "
    "Give access again once it is confirmed, in a few seconds."
)
_GRANT_EXPIRED = (
    "Your grant to {grantee} expired at {expiry:%Y-%m-%d %H:%M} UTC. To give access again, "
    "change that grant: a new expiry, or none."
)

# Which credential made a grant (Grant.made_with): a browser session, an owner API token, or an
# operator's command.
GRANT_MADE_WITH = ("session", "token", "cli")


def grant_create(
    *,
    owner: Owner,
    grantee: Owner,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
    terms: GrantTerms = ALL_RECORDS_FOREVER,
) -> Grant:
    """Let `grantee` read `owner`'s records (those `terms` cover, until its expiry);
    authorityGrant (authorityGrantScoped for limited terms) is sent on commit.

    `made_with` says which credential asked, `made_with_token` which owner API token (exactly
    when `made_with` is "token"), so that revoking the token can take its grants back.
    """
    _credential_check(owner, made_with, made_with_token)
    grant_create_check(owner=owner, grantee=grantee)
    try:
        with transaction.atomic():
            live = Grant.objects.filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
            _refuse_second_grant(live.first(), grantee)
            grant = Grant.objects.create(
                owner=owner,
                grantee=grantee,
                made_with=made_with,
                made_with_token=made_with_token,
                **_terms_fields(terms),
            )
            _grant_change_record(
                grant, GrantChange.Kind.CREATED, made_with, made_with_token, None, terms
            )
            transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
    except IntegrityError:
        # A simultaneous grant for the same pair won the race (one live grant per pair).
        raise AlreadyGranted(_ALREADY_GRANTED.format(grantee=grantee)) from None
    return grant


def _credential_check(owner: Owner, made_with: str, made_with_token: OwnerToken | None) -> None:
    if made_with not in GRANT_MADE_WITH or (made_with == "token") != (made_with_token is not None):
        raise ValueError(f"made_with is one of {GRANT_MADE_WITH}, with a token for 'token' only")
    if made_with_token is not None and made_with_token.owner_id != owner.pk:
        raise ValueError("a grant is changed with a token of its own owner")


def _grant_change_record(
    grant: Grant,
    kind: str,
    made_with: str,
    token: OwnerToken | None,
    before: GrantTerms | None,
    after: GrantTerms | None,
) -> None:
    GrantChange.objects.create(
        grant=grant,
        kind=kind,
        made_with=made_with,
        token=token,
        terms_before=None if before is None else before.as_json(),
        terms_after=None if after is None else after.as_json(),
    )


def grant_create_check(*, owner: Owner, grantee: Owner) -> None:
    """Why `grant_create` would refuse this pair, raised before anything is written (the
    grants page asks it before its confirmation step): a grant to oneself, an owner or grantee
    not registered on chain yet, or a live grant of the pair (grant_create checks that again
    in its transaction)."""
    if grantee.pk == owner.pk:
        raise SelfGrant("You always see your own records: name another owner.")
    if owner.chain_state != ChainState.CONFIRMED:
        raise NotRegisteredYet(
            "Your account is not registered on the chain yet: try again in a minute."
        )
    if grantee.chain_state != ChainState.CONFIRMED:
        raise GranteeNotRegistered(
            f"{grantee}'s account is not registered on the chain yet: try again in a minute."
        )
    live = Grant.objects.filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
    _refuse_second_grant(live.first(), grantee)


def _refuse_second_grant(live: Grant | None, grantee: Owner) -> None:
    """AlreadyGranted if the pair has a live grant. One past its expiry gives nothing, but it
    is the pair's grant still: renewed by a change of its terms, which the refusal says. One
    being revoked gives nothing either, and blocks a new grant until the chain has the
    revocation (RevocationPending)."""
    if live is None:
        return
    if live.status == Grant.Status.REVOKING:  # no access since the revocation: not "has access"
        raise RevocationPending(_REVOCATION_PENDING.format(grantee=grantee))
    if live.shown_status == "expired":  # the pages' word for it: pending or active, past expiry
        expiry = live.expires_at.astimezone(UTC)
        raise AlreadyGranted(_GRANT_EXPIRED.format(grantee=grantee, expiry=expiry))
    raise AlreadyGranted(_ALREADY_GRANTED.format(grantee=grantee))


def grant_terms_change(
    *,
    owner: Owner,
    grantee: Owner,
    terms: GrantTerms,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
) -> Grant:
    """Change what a live grant covers or when it expires: the portal enforces the new terms
    at once (the grant is pending until authorityGrantScoped, a new transaction, confirms
    them; meanwhile nothing of it can be read), and the chain follows.

    An owner API token may narrow any grant, but widen (more records, a later expiry or none)
    only a grant that it made and that no other credential has changed since: a stolen token
    cannot turn the owner's grant into "all records, never expires" (TokenCannotWiden).
    """
    _credential_check(owner, made_with, made_with_token)
    with transaction.atomic():
        grant = (
            Grant.objects.select_for_update()
            .filter(
                owner=owner, grantee=grantee, status__in=[Grant.Status.PENDING, Grant.Status.ACTIVE]
            )
            .first()
        )
        if grant is None:
            raise NoGrant(f"{grantee} has no access to change: give access first.")
        fields = _terms_fields(terms)
        if all(getattr(grant, name) == value for name, value in fields.items()):
            return grant  # the same terms: nothing to send
        before = GrantTerms.of(grant)
        if made_with_token is not None and not terms.within(before):
            _token_widening_check(grant, made_with_token, grantee)
        for name, value in fields.items():
            setattr(grant, name, value)
        grant.status = Grant.Status.PENDING
        grant.save(update_fields=[*fields, "status", "updated_at"])
        _grant_change_record(
            grant, GrantChange.Kind.CHANGED, made_with, made_with_token, before, terms
        )
        transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
        # The grantee's exports may hold records outside the new terms (sharing/exports.py).
        transaction.on_commit(lambda: enqueue(EXPORTS_RECHECK_TASK, grant.grantee_id))
    return grant


def _token_widening_check(grant: Grant, token: OwnerToken, grantee: Owner) -> None:
    """TokenCannotWiden unless `grant` is wholly `token`'s work: made with it, and every
    change since made with it too."""
    others = grant.changes.exclude(made_with="token", token=token)
    if grant.made_with_token_id == token.pk and not others.exists():
        return
    raise TokenCannotWiden(
        f"An API token can narrow your grant to {grantee} but not widen it (more records, a "
        "later expiry or none): it was given or changed in another way. Widen it on the "
        "grants page."
    )


def grant_revoke(
    *,
    owner: Owner,
    grantee: Owner,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
) -> Grant:
    """Take access away: refused by the portal at once, authorityRevoke sent on commit."""
    _credential_check(owner, made_with, made_with_token)
    with transaction.atomic():
        grant = (
            Grant.objects.select_for_update()
            .filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
            .first()
        )
        if grant is None or grant.status == Grant.Status.REVOKING:
            raise NoGrant(f"{grantee} has no access to revoke.")
        grant.status = Grant.Status.REVOKING
        grant.save(update_fields=["status", "updated_at"])
        _grant_change_record(
            grant,
            GrantChange.Kind.REVOKED,
            made_with,
            made_with_token,
            GrantTerms.of(grant),
            None,
        )
        grant_revoked_alert(grantee=grant.grantee, owner=owner)
        transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
        transaction.on_commit(lambda: enqueue(EXPORTS_RECHECK_TASK, grant.grantee_id))
    return grant


@dataclass(frozen=True)
class TokenGrantsUndone:
    """What grants_undo_made_with did: grants revoked, and grants given back their terms."""

    revoked: list[Grant]
    restored: list[Grant]


def grants_undo_made_with(
    *, token: OwnerToken, revoke_made: bool = True, restore_changed: bool = True
) -> TokenGrantsUndone:
    """Undo what `token` (revoked, perhaps stolen) did to its owner's grants, with the owner's
    session as the credential: every live grant it made is revoked (`revoke_made`), and every
    live grant it changed last is given back the terms it had before the token's changes
    (`restore_changed`), or revoked if those terms have expired meanwhile (docs/grants.md).
    Grants the token revoked stay revoked: giving access again is the owner's to do."""
    revoked: list[Grant] = []
    restored: list[Grant] = []
    owner = token.owner
    if restore_changed:
        for grant, before in grant_list_changed_with(token):
            terms = GrantTerms.from_json(before)
            try:
                if terms.expires_at is not None and terms.expires_at < (
                    timezone.now() + MIN_GRANT_LIFETIME
                ):
                    revoked.append(grant_revoke(owner=owner, grantee=grant.grantee))
                else:
                    restored.append(
                        grant_terms_change(owner=owner, grantee=grant.grantee, terms=terms)
                    )
            except NoGrant:
                continue  # revoked meanwhile by someone else
    if revoke_made:
        for grant in grant_list_made_with(token):
            try:
                revoked.append(grant_revoke(owner=owner, grantee=grant.grantee))
            except NoGrant:
                continue
    return TokenGrantsUndone(revoked=revoked, restored=restored)


# --- on chain (run by the worker) -----------------------------------------------------


def grant_sync_on_chain(*, grant_id: int) -> Grant:
    """Make the chain agree with the portal's grant: authorityGrant or authorityRevoke."""
    grant = Grant.objects.select_related("owner", "grantee").get(pk=grant_id)
    for party in (grant.owner, grant.grantee):
        if party.chain_state != ChainState.CONFIRMED:
            raise ChainWorkNotReady(f"{party} is not registered on chain yet")
    chain_work_check()  # nothing goes to a reset chain
    pair = f"grant:{grant.owner_id}:{grant.grantee_id}"
    with exclusive(pair, timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        grant.refresh_from_db()
        try:
            _grant_sync(grant)
        except InsufficientFunds:
            # The owner's account cannot pay for gas: the grant waits (no failure), says why,
            # and is sent again once the operator topped the account up.
            Grant.objects.filter(pk=grant.pk).update(failure_reason=WAITING_FOR_GAS)
            enqueue("accounts.tasks.owner_top_up", grant.owner_id)
            raise
        except TransactionReverted as exc:
            if grant.status != Grant.Status.PENDING:
                raise  # a revocation is never given up: it fails loudly and the sweep retries
            # The contract will refuse this grant every time: say so, do not retry forever.
            Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(
                status=Grant.Status.FAILED,
                failure_reason=GRANT_REFUSALS.get(exc.error_name, str(exc))[:300],
            )
            logger.error("grant %s refused on chain: %s", grant.pk, exc)
    Grant.objects.filter(pk=grant.pk, failure_reason=WAITING_FOR_GAS).update(failure_reason="")
    grant.refresh_from_db()
    return grant


# Why a scoped or expiring grant cannot be written to a contract deployed before they existed.
CONTRACT_WITHOUT_SCOPES = (
    "the contract deployed on this chain predates scoped and expiring grants: an operator must "
    'upgrade it (docs/grants.md, "Upgrading a deployment"); a grant of all records without '
    "expiry works meanwhile"
)


# The chain's refusals of a grant that the owner can act on, in words.
GRANT_REFUSALS = {
    "ScopedGrantsUnsupported": CONTRACT_WITHOUT_SCOPES,
    "ExpiryInPast": "the expiry passed before the grant reached the chain: give access again "
    "with a later expiry",
}


def _grant_sync(grant: Grant) -> None:
    client = chain_client()
    owner, grantee = grant.owner, grant.grantee
    on_chain = client.grant_of(owner.eoa_address, grantee.eoa_address)
    if on_chain is None:  # a contract from before scoped grants
        has_access = client.has_access(owner.eoa_address, grantee.eoa_address)
        exists, same_terms = has_access, has_access
    else:
        has_access = on_chain.live
        # An expired grant is still there (its terms are nonzero) until revoked.
        exists = on_chain.live or on_chain.expiry != 0 or on_chain.scope != ALL_RECORDS_COMMITMENT
        same_terms = (
            on_chain.live
            and on_chain.scope == scope_commitment(grant.scope)
            and on_chain.expiry == grant.expiry
        )
    if grant.status == Grant.Status.PENDING:
        fields: dict[str, object] = {"status": Grant.Status.ACTIVE}
        if not same_terms:
            if on_chain is None and grant.is_limited:
                raise TransactionReverted("ScopedGrantsUnsupported")
            account = owner_eoa_account(owner)
            if not exists and not grant.is_limited:
                # The plain grant of DESIGN.md, as before scopes: all records, no expiry.
                send, tolerated = (
                    lambda: client.authority_grant(account, grantee.eoa_address),
                    "AlreadyGranted",
                )
            else:
                send, tolerated = (
                    lambda: client.authority_grant_scoped(
                        account,
                        grantee.eoa_address,
                        scope_commitment(grant.scope),
                        grant.expiry,
                    ),
                    "SameTerms",
                )
            result = _tolerating(tolerated, send)
            if result is not None:
                fields.update(grant_tx=result.tx_hash, grant_block=result.block_number)
                _grant_activity_record(grant, ChainActivity.Kind.GRANTED, result)
        if Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(**fields):
            grant_received_alert(grantee=grantee, owner=owner)
    elif grant.status == Grant.Status.REVOKING:
        fields = {"status": Grant.Status.REVOKED}
        if exists:
            result = _tolerating(
                "NoGrant",
                lambda: client.authority_revoke(owner_eoa_account(owner), grantee.eoa_address),
            )
            if result is not None:
                fields.update(revoke_tx=result.tx_hash, revoke_block=result.block_number)
                _grant_activity_record(grant, ChainActivity.Kind.REVOKED, result)
        Grant.objects.filter(pk=grant.pk, status=Grant.Status.REVOKING).update(**fields)


def _grant_activity_record(grant: Grant, kind: str, result: TxResult) -> None:
    """The audit page's entry of a grant or revocation, for the owner and the grantee."""
    chain_activity_record(
        owner=grant.owner,
        counterpart=grant.grantee,
        kind=kind,
        tx_hash=result.tx_hash,
        block_number=result.block_number,
    )


def _tolerating(error_name: str, send: Callable[[], TxResult]) -> TxResult | None:
    """Send; a refusal meaning "already the case" (a lost race) counts as done."""
    try:
        return send()
    except TransactionReverted as exc:
        if exc.error_name == error_name:
            return None
        raise


def chain_work_sweep() -> dict[str, int]:
    """Queue again anchoring and grants pending for longer than ANCHOR_STALE_AFTER (a lost
    message, a dead worker); their tasks are idempotent."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    owners = set(
        Record.objects.filter(status=Record.Status.PENDING, created_at__lt=cutoff).values_list(
            "owner_id", flat=True
        )
    )
    for owner_id in owners:
        anchor_schedule(owner_id=owner_id)
    grants = list(
        Grant.objects.filter(
            status__in=[Grant.Status.PENDING, Grant.Status.REVOKING], updated_at__lt=cutoff
        ).values_list("pk", flat=True)
    )
    for grant_pk in grants:
        enqueue("sharing.tasks.grant_sync", grant_pk)
    return {"anchor_owners": len(owners), "grants": len(grants)}
