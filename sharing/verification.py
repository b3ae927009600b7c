"""The integrity check at view time, and reading a record's content through it.

The worker runs `record_verify`: access on chain, one fetch of the stored envelope (Redis
cache, else durable storage), one SM3 hash, compared with the digest on chain; it leaves a
Verdict and hands back the bytes it checked. The web process (`record_open`) decrypts those
very bytes, and only when the verdict is `verified`; a refusal carries its record and verdict.
Several records for one viewer (a trajectory) are checked in one run, `records_verify`.
"""

import base64
import dataclasses
import logging
import uuid
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.utils import timezone
from redis.exceptions import RedisError

from accounts.errors import IdentityMismatch
from accounts.identity import owner_identity_check
from accounts.models import Owner, OwnerKey, OwnerToken
from accounts.selectors import owner_key_by_id, owner_key_bytes, owner_key_current
from alerts.services import record_tampered_alert
from chainworker.chain import AuthROSChain, RobotKeyOnChain
from chainworker.services import chain_client, chain_head
from core.outbox import dispatch
from sharing.cache import envelope_cache_evict, envelope_fetch
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
from sharing.models import Grant, Record, SecurityEvent, Verdict
from sharing.roots import record_path
from sharing.scope import scope_commitment
from sharing.selectors import (
    grant_live,
    record_deletion_text,
    record_get_visible,
    record_to_check,
    record_to_open,
    record_topic_history,
    verdict_by_id,
)
from smcrypto import envelope, provenance, sm3
from smcrypto.merkle import leaf_hash, proof_holds

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

VERIFY_TASK = "sharing.tasks.record_verify"
VERIFY_MANY_TASK = "sharing.tasks.records_verify"


# --- the check, in the worker ------------------------------------------------------------------


@dataclass(frozen=True)
class Verification:
    verdict: Verdict
    envelope: bytes | None  # the bytes that were checked; only when verified


def record_verify(
    *,
    record_id: uuid.UUID | str,
    viewer_id: int,
    checked_by_id: int | None = None,
    credential: str = Verdict.Credential.UNKNOWN,
    token_id: int | None = None,
) -> Verification:
    """Check access on chain and the stored envelope's SM3 digest against the chain.

    Every check leaves a Verdict: the audit trail of who viewed what, when, and the chain's
    head then (as last seen by the portal, at most IDENTITY_BLOCK_CACHE_SECONDS old).
    `checked_by_id` names the operator running the check with the viewer's rights (the admin
    console's re-verify), so that it is not recorded as the viewer's own view. `credential`
    and `token_id` say which credential of the viewer asked (the access log's "from which
    credential"); an operator's check is always `operator`.
    """
    if checked_by_id is not None:
        credential, token_id = Verdict.Credential.OPERATOR, None
    _credential_check(credential, token_id)
    record = record_to_check(record_id)
    viewer = Owner.objects.get(pk=viewer_id)
    client = chain_client()
    block = chain_head(client)

    def verdict(outcome: str, **fields: object) -> Verdict:
        return Verdict.objects.create(
            record=record,
            viewer=viewer,
            checked_by_id=checked_by_id,
            record_owner_id=record.owner_id,
            credential=credential,
            token_id=token_id,
            outcome=outcome,
            block_number=_verdict_block(block, record),
            **fields,
        )

    if not _may_view_identified(record, viewer, client):
        coalesced = None if checked_by_id is not None else _refused_lately(record, viewer)
        return Verification(coalesced or verdict(Verdict.Outcome.NO_ACCESS), None)
    if record.is_deleted:
        return Verification(verdict(Verdict.Outcome.DELETED), None)
    fields, data = _digest_check(record, viewer, client)
    return Verification(verdict(**fields), data)


# Refused views of one owner's records by one viewer in a row leave one verdict (a row in both
# access logs) per this long: the first; later ones are answered the same and not written, so
# an owner without a grant cannot fill another owner's access log (docs/security.md). A view
# that passed in between starts a new row.
REFUSED_VIEWS_COALESCED = timedelta(hours=1)


def _refused_lately(record: Record, viewer: Owner) -> Verdict | None:
    """The viewer's last own view of a record of the same owner, if it was refused within
    REFUSED_VIEWS_COALESCED."""
    last = (
        Verdict.objects.filter(
            viewer=viewer,
            record_owner_id=record.owner_id,
            checked_by__isnull=True,
            created_at__gte=timezone.now() - REFUSED_VIEWS_COALESCED,
        )
        .order_by("-created_at", "-pk")
        .first()
    )
    return last if last is not None and last.outcome == Verdict.Outcome.NO_ACCESS else None


def records_verify(
    *,
    record_ids: Sequence[uuid.UUID | str],
    viewer_id: int,
    credential: str = Verdict.Credential.UNKNOWN,
    token_id: int | None = None,
) -> list[Verification]:
    """record_verify for several records of one viewer in one run (a trajectory's poses).

    One chain head, one access check per record owner, one digest read on chain per record,
    and every verdict written in one INSERT. One Verification per record that exists, in the
    order asked.
    """
    _credential_check(credential, token_id)
    wanted = [uuid.UUID(str(record_id)) for record_id in record_ids]
    # The robot too: a signed record's check reads its public key.
    found = Record.objects.select_related("owner", "anchor_root", "robot").in_bulk(wanted)
    records = [found[record_id] for record_id in wanted if record_id in found]
    viewer = Owner.objects.get(pk=viewer_id)
    client = chain_client()
    block = chain_head(client)
    grants: dict[int, Grant | None] = {}  # per owner: the grant checked on chain, if it holds
    robot_keys: dict[str, RobotKeyOnChain] = {}  # per signer: robotKeyOf, asked once
    identified: set[int] = set()
    checked: list[tuple[dict[str, object], bytes | None]] = []
    for record in records:
        if record.owner_id not in grants:
            grants[record.owner_id] = _grant_checked(record, viewer, client)
        grant = grants[record.owner_id]
        if grant is not None and _in_scope(grant, record) and record.is_deleted:
            checked.append(({"outcome": Verdict.Outcome.DELETED}, None))
        elif grant is not None and _in_scope(grant, record):
            if record.owner_id not in identified:
                owner_identity_check(owner=record.owner)
                identified.add(record.owner_id)
            checked.append(_digest_check(record, viewer, client, robot_keys))
        else:
            checked.append(({"outcome": Verdict.Outcome.NO_ACCESS}, None))
    verdicts = Verdict.objects.bulk_create(
        Verdict(
            record=record,
            viewer=viewer,
            record_owner_id=record.owner_id,
            credential=credential,
            token_id=token_id,
            block_number=_verdict_block(block, record),
            **fields,
        )
        for record, (fields, _data) in zip(records, checked, strict=True)
    )
    return [
        Verification(verdict, data)
        for verdict, (_fields, data) in zip(verdicts, checked, strict=True)
    ]


def _credential_check(credential: str, token_id: int | None) -> None:
    """A verdict's credential is one of Verdict.Credential, with a token exactly for `token`."""
    if credential not in Verdict.Credential.values:
        raise ValueError(f"unknown credential {credential!r}")
    if (credential == Verdict.Credential.TOKEN) != (token_id is not None):
        raise ValueError("a token id goes with the `token` credential, and only with it")


def _verdict_block(head: int, record: Record) -> int:
    """The block a verdict states: the chain's head as the portal last saw it, never below the
    block the record was anchored in (which the chain answering for it must have)."""
    return max(head, record.block_number or 0)


def _digest_check(
    record: Record,
    viewer: Owner,
    client: AuthROSChain,
    robot_keys: dict[str, RobotKeyOnChain] | None = None,
) -> tuple[dict[str, object], bytes | None]:
    """The stored envelope's SM3 digest against the chain's, then its robot signature: the
    verdict's fields, and the bytes checked when both hold. `robot_keys` keeps the chain's
    answer per signer across the records of one run."""
    fields, data = _anchored_check(record, viewer, client)
    if data is None or _provenance_holds(
        record, data, client, {} if robot_keys is None else robot_keys
    ):
        return fields, data
    security_log.error(
        "record %s is anchored but its robot signature does not hold (signer %r)",
        record.pk,
        record.signer,
    )
    return {**fields, "outcome": Verdict.Outcome.SIGNATURE_REFUSED}, None


def _provenance_holds(
    record: Record, data: bytes, client: AuthROSChain, robot_keys: dict[str, RobotKeyOnChain]
) -> bool:
    """DESIGN.md "Provenance": the anchored envelope names the signer the record was stored
    with; a signed record's key is its owner's on chain (robotKeyOf), added at or before the
    record's anchoring block and not revoked by then, hashes to `signer`, and its signature
    holds over the decrypted content. An unsigned record (a robot added by hand) holds as
    unsigned: pages and answers say so, never "genuine"."""
    header = envelope.read_header(data).header
    signer = header.get("signer", "")
    if signer != record.signer:
        return False
    if not signer:
        return True
    if signer not in robot_keys:
        robot_keys[signer] = client.robot_key_of(bytes.fromhex(signer))
    on_chain = robot_keys[signer]
    public_key = record.robot.public_key
    return (
        on_chain.owner is not None
        and on_chain.owner.lower() == record.owner.eoa_address.lower()
        and record.block_number is not None
        and on_chain.live_at(record.block_number)
        and bool(public_key)
        and provenance.key_hash(public_key) == signer
        and provenance.verify_header(public_key, header, envelope.open(record_key(record), data)[1])
    )


def record_signature(record: Record, data: bytes, client: AuthROSChain) -> dict[str, Any] | None:
    """What a record's proof says of its robot signature (DESIGN.md "Provenance"): the signer
    and signature the stored envelope names, the robot's public key, and the key's owner and
    blocks as the chain holds them; None for an unsigned record. Facts for the caller to check,
    not a verdict."""
    header = envelope.read_header(data).header
    signer = header.get("signer")
    if not signer:
        return None
    on_chain = client.robot_key_of(bytes.fromhex(signer))
    public_key = record.robot.public_key
    return {
        "signer": signer,
        "public_key": public_key if public_key.startswith("04") else "04" + public_key,
        "sig": header.get("sig", ""),
        "key_owner": on_chain.owner,
        "key_added_block": on_chain.added_block if on_chain.owner else None,
        "key_revoked_block": on_chain.revoked_block,
    }


def _anchored_check(
    record: Record, viewer: Owner, client: AuthROSChain
) -> tuple[dict[str, object], bytes | None]:
    """The stored envelope's SM3 digest against the chain's: the verdict's fields, and the
    bytes checked when they match."""
    try:
        data, source = envelope_fetch(record)
    except FileNotFoundError:
        if Record.objects.filter(pk=record.pk, deleted_at__isnull=False).exists():
            # Deleted while this check ran: its ciphertext was removed on purpose.
            return {"outcome": Verdict.Outcome.DELETED, "source": "storage"}, None
        # The durable copy is gone, removed behind the portal's back: nothing is left that
        # hashes to the digest the chain holds.
        _record_tampered(record, viewer, source="storage", computed="missing", chain="")
        return {"outcome": Verdict.Outcome.TAMPERED, "source": "storage"}, None
    computed = sm3.sm3_hex(data)
    if record.anchor_root_id is not None:
        return _proof_check(record, viewer, client, data=data, source=source, computed=computed)
    on_chain = client.data_query(record.id, owner=record.owner.eoa_address)
    if on_chain is None:
        fields = {"computed_digest": computed, "source": source}
        return {"outcome": Verdict.Outcome.NOT_ANCHORED_YET, **fields}, None
    chain_digest = on_chain.digest.hex()
    fields = {"computed_digest": computed, "chain_digest": chain_digest, "source": source}
    if chain_digest != computed or on_chain.owner.lower() != record.owner.eoa_address.lower():
        _record_tampered(record, viewer, source=source, computed=computed, chain=chain_digest)
        return {"outcome": Verdict.Outcome.TAMPERED, **fields}, None
    return {"outcome": Verdict.Outcome.VERIFIED, **fields}, data


def _proof_check(
    record: Record,
    viewer: Owner,
    client: AuthROSChain,
    *,
    data: bytes,
    source: str,
    computed: str,
) -> tuple[dict[str, object], bytes | None]:
    """Root mode: the record's leaf (owner, id, the stored envelope's SM3) folded up its audit
    path must give its tree's root, which the owner's account anchored with the same size:
    one eth_call (rootOf), no per-record storage on chain."""
    tree = record.anchor_root
    fields = {"computed_digest": computed, "source": source}
    on_chain = client.root_of(tree.sender, bytes.fromhex(tree.root))
    if on_chain is None:
        return {"outcome": Verdict.Outcome.NOT_ANCHORED_YET, **fields}, None
    # The digest the portal stored is the one its tree holds iff the stored proof folds to
    # the anchored root; the envelope is intact iff it hashes to that digest.
    anchored = (
        proof_holds(
            leaf_hash(tree.sender, record.id, bytes.fromhex(record.digest)),
            record.leaf_index if record.leaf_index is not None else -1,
            on_chain.size,
            record_path(record),
            bytes.fromhex(tree.root),
        )
        and on_chain.size == tree.size
        and tree.sender.lower() == record.owner.eoa_address.lower()
    )
    chain_digest = record.digest if anchored else ""
    fields["chain_digest"] = chain_digest
    if computed != chain_digest:
        _record_tampered(record, viewer, source=source, computed=computed, chain=chain_digest)
        return {"outcome": Verdict.Outcome.TAMPERED, **fields}, None
    return {"outcome": Verdict.Outcome.VERIFIED, **fields}, data


def verification_answer(verification: Verification) -> dict[str, Any]:
    """What the worker hands back to the view (JSON through the result backend)."""
    data = verification.envelope
    return {
        "record_id": str(verification.verdict.record_id),
        "verdict_id": verification.verdict.pk,
        "outcome": verification.verdict.outcome,
        "envelope": base64.b64encode(data).decode("ascii") if data is not None else None,
    }


def _may_view_identified(record: Record, viewer: Owner, client: AuthROSChain) -> bool:
    """_may_view, and for a viewer who may, the identity check of the record's owner: a
    commitment on chain that is not the key the portal holds raises IdentityMismatch."""
    if not _may_view(record, viewer, client):
        return False
    owner_identity_check(owner=record.owner)
    return True


def _may_view(record: Record, viewer: Owner, client: AuthROSChain) -> bool:
    """The owner, or a grantee whose grant is live in the portal and on chain, with the same
    terms in both, and covers the record."""
    grant = _grant_checked(record, viewer, client)
    return grant is not None and _in_scope(grant, record)


# The owner's own records need no grant: _grant_checked answers this for the owner.
_OWN = Grant(status=Grant.Status.ACTIVE)


def _grant_checked(record: Record, viewer: Owner, client: AuthROSChain) -> Grant | None:
    """The grant that lets `viewer` read the record owner's records, if it holds in the
    portal (active, not expired) and on chain (grantOf, one eth_call: live at the latest
    block, the same scope commitment and expiry as the portal's); _OWN for the owner."""
    if viewer.pk == record.owner_id:
        return _OWN
    grant = grant_live(owner_id=record.owner_id, viewer=viewer)
    if grant is None:
        return None
    owner_eoa, viewer_eoa = record.owner.eoa_address, viewer.eoa_address
    on_chain = client.grant_of(owner_eoa, viewer_eoa)
    if on_chain is None:  # a contract from before scoped grants: only plain grants hold
        holds = not grant.is_limited and client.has_access(owner_eoa, viewer_eoa)
    else:
        holds = (
            on_chain.live
            and on_chain.scope == scope_commitment(grant.scope)
            and on_chain.expiry == grant.expiry
        )
    if not holds:
        logger.info("grant %s does not hold on chain as the portal has it", grant.pk)
        return None
    return grant


def _in_scope(grant: Grant, record: Record) -> bool:
    return grant is _OWN or grant.scope.covers(
        robot_id=record.robot_id, topic=record.topic, captured_at=record.captured_at
    )


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
    record_tampered_alert(
        owner=record.owner,
        record_id=record.pk,
        topic=record.topic,
        robot=record.robot.name,
        source=source,
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
    # With record_open(earlier=n): the earlier records of its topic, oldest first.
    earlier: list["OpenedRecord | SharingError"] = dataclasses.field(default_factory=list)


def record_open(
    *,
    record_id: uuid.UUID | str,
    viewer: Owner,
    earlier: int = 0,
    credential: str = Verdict.Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> OpenedRecord:
    """Have the worker check the record, then decrypt what it checked.

    With `earlier`, up to that many earlier records of its topic (record_topic_history) are
    checked in the same run and opened into `OpenedRecord.earlier`: a trajectory is one
    check, not one per pose. `credential` (and `token`, an owner API token's) is the
    viewer's credential that asked, kept on the verdicts for the access log.

    Raises RecordNotFound, VerificationUnavailable, RecordDeleted (with the record: its
    ciphertext is gone, nothing is checked), or (with the record and the verdict attached)
    AccessDenied, IntegrityCheckFailed or NotAnchoredYet.
    """
    _credential_check(credential, _token_id(token))
    try:
        record = record_to_open(uuid.UUID(str(record_id)))
    except ValueError:
        record = None
    if record is None:
        raise RecordNotFound(NOT_VISIBLE)
    if record.is_deleted:
        if record.owner_id != viewer.pk and record_get_visible(viewer, record.pk) is None:
            raise RecordNotFound(NOT_VISIBLE)  # "deleted" would tell it existed
        raise _deleted(record)
    if earlier <= 0:
        pending = _send(VERIFY_TASK, str(record.pk), viewer.pk, credential, _token_id(token))
        # While the worker checks: the record's key, looked up and unwrapped meanwhile.
        key = _record_key_early(record)
        return _opened(record, viewer, pending, key)
    *before, own = record_open_many(
        records=record_topic_history(record, limit=earlier + 1, viewer=viewer),
        viewer=viewer,
        credential=credential,
        token=token,
    )
    if isinstance(own, SharingError):
        raise own
    return dataclasses.replace(own, earlier=before)


def record_open_many(
    *,
    records: Sequence[Record],
    viewer: Owner,
    credential: str = Verdict.Credential.UNKNOWN,
    token: OwnerToken | None = None,
) -> list[OpenedRecord | SharingError]:
    """record_open for several records at once, in one check on the worker
    (`records_verify`). One result per record, in order: the opened record, or the
    SharingError record_open would have raised."""
    _credential_check(credential, _token_id(token))
    if not records:
        return []
    ids = [str(record.pk) for record in records]
    pending = _send(VERIFY_MANY_TASK, ids, viewer.pk, credential, _token_id(token))
    try:
        answers = _await_answer(pending, f"{len(records)} records", viewer)
    except VerificationUnavailable as exc:
        return [VerificationUnavailable(str(exc)) for _ in records]
    by_record = {answer["record_id"]: answer for answer in answers}
    verdicts = Verdict.objects.in_bulk([answer["verdict_id"] for answer in answers])
    results: list[OpenedRecord | SharingError] = []
    for record in records:
        answer = by_record.get(str(record.pk))
        try:
            if answer is None:  # deleted meanwhile
                raise RecordNotFound("no such record")
            results.append(_decrypted(record, verdicts[answer["verdict_id"]], _envelope_of(answer)))
        except SharingError as exc:
            results.append(exc)
    return results


def record_reseal_for(*, opened: OpenedRecord, viewer: Owner) -> bytes:
    """The record's content sealed under the viewer's own current key (same header)."""
    return envelope.seal(
        owner_key_bytes(owner_key_current(viewer)), opened.header, opened.plaintext
    )


def _token_id(token: OwnerToken | None) -> int | None:
    return token.pk if token is not None else None


def _send(task_name: str, *args: Any) -> Any:
    """Queue the worker's integrity check; an exception instead if it cannot be queued."""
    try:
        return dispatch(task_name, *args)
    except Exception as exc:  # the broker is down
        return exc


def _opened(record: Record, viewer: Owner, pending: Any, key: bytes | None) -> OpenedRecord:
    answer = _await_answer(pending, str(record.pk), viewer)
    return _decrypted(record, verdict_by_id(answer["verdict_id"]), _envelope_of(answer), key=key)


def record_key(record: Record) -> bytes:
    """The SM4 key the record was sealed under."""
    key = owner_key_by_id(record.owner, record.key_id)
    if key is None:
        raise OwnerKey.DoesNotExist(f"no key {record.key_id} of the record's owner")
    return owner_key_bytes(key)


def _record_key_early(record: Record) -> bytes | None:
    """record_key while the worker checks; None if it fails now (the check's verdict
    comes first: _decrypted asks again only for a record it may show)."""
    try:
        return record_key(record)
    except OwnerKey.DoesNotExist:  # reported where the record is opened, as before
        return None


def _decrypted(
    record: Record, verdict: Verdict, data: bytes | None, *, key: bytes | None = None
) -> OpenedRecord:
    """The record decrypted from the bytes the worker checked, if its verdict allows."""
    if verdict.outcome == Verdict.Outcome.NO_ACCESS:
        raise AccessDenied(NOT_VISIBLE, record=record, verdict=verdict)
    if verdict.outcome == Verdict.Outcome.DELETED:
        record.refresh_from_db()
        raise _deleted(record, verdict)
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
    header, plaintext = envelope.open(key if key is not None else record_key(record), data)
    return OpenedRecord(record, verdict, header, plaintext, data)


def _deleted(record: Record, verdict: Verdict | None = None) -> RecordDeleted:
    return RecordDeleted(record_deletion_text(record), record=record, verdict=verdict)


def _await_answer(pending: Any, what: str, viewer: Owner) -> Any:
    """The worker's answer (verification_answer, or a list of them); VerificationUnavailable
    if it cannot be had."""
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
    except IdentityMismatch:
        raise  # the worker's refusal: the owner's commitment on chain is not the portal's key
    except Exception as exc:  # timeout, broker down, or the worker's own failure
        logger.warning("verification of %s for %s failed: %s", what, viewer, exc)
        raise VerificationUnavailable(
            "the integrity check could not run now; nothing is shown: try again shortly"
        ) from exc
    return answer


def _envelope_of(answer: dict[str, Any]) -> bytes | None:
    """The bytes the worker checked, when it found them verified."""
    encoded = answer.get("envelope")
    return base64.b64decode(encoded) if encoded is not None else None
