"""The integrity check at view time, and reading records' content through it: one path for
any number of records, the single record being N = 1.

The worker runs `records_verify` for a batch of records of one viewer: one chain head, one grant
check per record owner (access first, so that a viewer without access learns nothing, not
even that a record was deleted), the owner's identity check once, then per record one fetch of
the stored envelope (Redis cache, else durable storage) and one SM3 hash, compared with the
chain: one `rootOf` per distinct Merkle root (the records of one tree share it), `robotKeyOf`
once per signer; every verdict is written in one bulk INSERT and points to its Access (the line
the owner's access log shows: a page, a plot, an export...). It hands back the bytes it
checked. The web process (`records_open`, and `record_open` for one record) writes the Access,
sends the records in batches of VERIFY_BATCH (so that a plot of 18,000 records is checked by
every verify worker side by side) and decrypts those very bytes, only where the verdict is
`verified`; a refusal carries its record and verdict.
"""

import base64
import logging
import uuid
from collections import defaultdict
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import transaction
from django.utils import timezone
from redis.exceptions import RedisError

from accounts.errors import IdentityMismatch
from accounts.identity import owner_identity_check
from accounts.models import Owner, OwnerKey, OwnerToken
from accounts.selectors import owner_key_by_id, owner_key_bytes, owner_key_current
from alerts.services import record_tampered_alert
from chainworker.client import AuthROSChain
from chainworker.codec import OnChainRoot, RobotKeyOnChain
from chainworker.services import chain_client, chain_head
from core.outbox import dispatch
from sharing.cache import envelope_cache_evict, envelopes_fetch
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
from sharing.models import Access, Grant, Record, SecurityEvent, Verdict
from sharing.roots import record_path
from sharing.scope import scope_commitment
from sharing.selectors import (
    grant_live,
    record_deletion_text,
    record_to_check,
    record_to_open,
    records_to_check,
)
from smcrypto import envelope, provenance, sm3
from smcrypto.errors import CryptoError, SignatureInvalid
from smcrypto.merkle import leaf_hash, proof_holds

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

VERIFY_TASK = "sharing.tasks.records_verify"
# Records per task: a bigger read is sent as several tasks at once, which the verify workers
# take side by side; each answer holds its batch's envelopes (about 1 KB each for odometry).
VERIFY_BATCH = 1000


# --- the check, in the worker ------------------------------------------------------------------


@dataclass(frozen=True)
class Verification:
    verdict: Verdict
    envelope: bytes | None  # the bytes that were checked; only when verified
    # Those bytes opened (header, plaintext), when the check decrypted them for the robot
    # signature (a signed record's); for a reader in the same process to use, never sent.
    opened: tuple[dict, bytes] | None = None


class _ChainReads:
    """What one run of checks reads from the chain, each asked once in the run: the grant per
    record owner, the owner's identity, `rootOf` per tree and `robotKeyOf` per signer; and
    the records' keys (to check a signature over the plaintext), unwrapped once per key."""

    def __init__(self, client: AuthROSChain) -> None:
        self.client = client
        self.keys = RecordKeys()
        self.grants: dict[int, Grant | None] = {}
        self.identified: set[int] = set()
        self.roots: dict[tuple[str, str], OnChainRoot | None] = {}
        self.robot_keys: dict[str, RobotKeyOnChain] = {}
        # The signed envelopes the run opened to check their signatures, by record.
        self.opened: dict[uuid.UUID, tuple[dict, bytes]] = {}

    def grant(self, record: Record, viewer: Owner) -> Grant | None:
        if record.owner_id not in self.grants:
            self.grants[record.owner_id] = _grant_checked(record, viewer, self.client)
        return self.grants[record.owner_id]

    def identify(self, owner: Owner) -> None:
        """The owner's identity check (IdentityMismatch if it fails), once per run."""
        if owner.pk not in self.identified:
            owner_identity_check(owner=owner)
            self.identified.add(owner.pk)

    def root_of(self, sender: str, root: str) -> OnChainRoot | None:
        if (sender, root) not in self.roots:
            self.roots[sender, root] = self.client.root_of(sender, bytes.fromhex(root))
        return self.roots[sender, root]

    def robot_key_of(self, signer: str) -> RobotKeyOnChain:
        if signer not in self.robot_keys:
            self.robot_keys[signer] = self.client.robot_key_of(bytes.fromhex(signer))
        return self.robot_keys[signer]


def records_verify(
    *,
    record_ids: Sequence[uuid.UUID | str] = (),
    records: Sequence[Record] | None = None,
    viewer_id: int,
    credential: str = Verdict.Credential.UNKNOWN,
    token_id: int | None = None,
    checked_by_id: int | None = None,
    kind: str | None = None,
    accesses: dict[int, int] | None = None,
) -> list[Verification]:
    """Check access on chain and each stored envelope's SM3 digest against the chain, for the
    records of one viewer; one Verification per record that exists, in the order asked.

    Per record, in this order: access (the owner, or a grant live in the portal and on chain
    that covers it: otherwise `no_access`, whatever else holds), deleted, the owner's identity
    (IdentityMismatch), then the stored envelope against the chain and its robot signature.
    Every check leaves a Verdict (the trail of who viewed what, when, and the chain's head
    then, as last seen by the portal), all in one INSERT, each pointing to its Access:
    `accesses` (record owner id -> Access id) when the web process opened them for a read it
    split into batches, else opened here, of `kind` (by default a view of one record, a page
    of several, an operator's check). `checked_by_id` names the operator running the check with
    the viewer's rights (the admin console's re-verify), recorded as `operator`, never as the
    viewer's own view; `credential` and `token_id` say which credential of the viewer asked.
    `records`, instead of `record_ids`: the records already read with their owner, robot and
    tree (an export's batch), checked as they are, not read again.
    """
    if checked_by_id is not None:
        credential, token_id = Verdict.Credential.OPERATOR, None
    _credential_check(credential, token_id)
    if kind is not None and kind not in Access.Kind.values:
        raise ValueError(f"unknown access kind {kind!r}")
    if records is None and len(record_ids) == 1:  # a view of one record: one fixed query
        found_one = record_to_check(uuid.UUID(str(record_ids[0])))
        records = [found_one] if found_one is not None else []
    if records is None:
        wanted = [uuid.UUID(str(record_id)) for record_id in record_ids]
        found = records_to_check(Record.objects.all()).in_bulk(wanted)
        records = [found[record_id] for record_id in wanted if record_id in found]
    viewer = Owner.objects.get(pk=viewer_id)
    reads = _ChainReads(chain_client())
    block = chain_head(reads.client)
    checked = _records_check(records, viewer, reads)
    again = _refused_again(records, checked, viewer, checked_by_id=checked_by_id, accesses=accesses)
    if again is not None:  # answered as the refused view before it, not written again
        return [Verification(again, None)]
    with transaction.atomic():  # the access line and its verdicts: one commit
        if accesses is None:  # opened once the checks ran: a check that raised leaves no line
            accesses = accesses_open(
                kind=kind or _kind_of(len(records), checked_by_id),
                viewer_id=viewer_id,
                records=records,
                credential=credential,
                token_id=token_id,
                checked_by_id=checked_by_id,
            )
        verdicts = Verdict.objects.bulk_create(
            Verdict(
                record=record,
                viewer=viewer,
                checked_by_id=checked_by_id,
                record_owner_id=record.owner_id,
                access_id=accesses.get(record.owner_id),
                credential=credential,
                token_id=token_id,
                block_number=_verdict_block(block, record),
                **fields,
            )
            for record, (fields, _data) in zip(records, checked, strict=True)
        )
    return [
        Verification(verdict, data, reads.opened.get(verdict.record_id) if data else None)
        for verdict, (_fields, data) in zip(verdicts, checked, strict=True)
    ]


# Refused views of one owner's records by one viewer in a row leave one verdict and access line
# (in both access logs) per this long: the first; later ones are answered the same and not
# written, so an owner without a grant cannot fill another owner's access log
# (docs/security.md). A view that passed in between starts a new line.
REFUSED_VIEWS_COALESCED = timedelta(hours=1)


def _refused_again(
    records: Sequence[Record],
    checked: Sequence[tuple[dict[str, object], bytes | None]],
    viewer: Owner,
    *,
    checked_by_id: int | None,
    accesses: dict[int, int] | None,
) -> Verdict | None:
    """For a viewer's own view of one record that is refused: the viewer's last own view of a
    record of the same owner, if it was refused within REFUSED_VIEWS_COALESCED."""
    if checked_by_id is not None or accesses is not None or len(records) != 1:
        return None
    if checked[0][0]["outcome"] != Verdict.Outcome.NO_ACCESS:
        return None
    last = (
        Verdict.objects.filter(
            viewer=viewer,
            record_owner_id=records[0].owner_id,
            checked_by__isnull=True,
            created_at__gte=timezone.now() - REFUSED_VIEWS_COALESCED,
        )
        .order_by("-created_at", "-pk")
        .first()
    )
    return last if last is not None and last.outcome == Verdict.Outcome.NO_ACCESS else None


def _kind_of(count: int, checked_by_id: int | None) -> str:
    if checked_by_id is not None:
        return Access.Kind.CHECK
    return Access.Kind.VIEW if count == 1 else Access.Kind.PAGE


def accesses_open(
    *,
    kind: str,
    viewer_id: int,
    records: Sequence[Record],
    credential: str,
    token_id: int | None,
    checked_by_id: int | None = None,
) -> dict[int, int]:
    """The access log's line for a read of these records: one Access per record owner (so that
    each owner's log is one range), naming how many of the owner's records it read, the record
    when it is one, the robot and topic when they all share them. Record owner id -> Access id."""
    by_owner: dict[int, list[Record]] = defaultdict(list)
    for record in records:
        by_owner[record.owner_id].append(record)
    reads = [
        OwnerRead(
            owner_id=owner_id,
            count=len(owned),
            record=owned[0] if len(owned) == 1 else None,
            robot_id=_shared({record.robot_id for record in owned}),
            topic=_shared({record.topic for record in owned}),
        )
        for owner_id, owned in by_owner.items()
    ]
    return accesses_open_for(
        kind=kind,
        viewer_id=viewer_id,
        reads=reads,
        credential=credential,
        token_id=token_id,
        checked_by_id=checked_by_id,
    )


@dataclass(frozen=True)
class OwnerRead:
    """What one read takes of one owner's records: how many, the record when it is one, the
    robot and the topic when they all share them (an export counts them in the database)."""

    owner_id: int
    count: int
    record: Record | None
    robot_id: uuid.UUID | None
    topic: str | None


def accesses_open_for(
    *,
    kind: str,
    viewer_id: int,
    reads: Sequence[OwnerRead],
    credential: str,
    token_id: int | None,
    checked_by_id: int | None = None,
) -> dict[int, int]:
    """accesses_open for reads already summed up per owner. Record owner id -> Access id."""
    rows = [
        Access(
            kind=kind,
            viewer_id=viewer_id,
            record_owner_id=read.owner_id,
            checked_by_id=checked_by_id,
            credential=credential,
            token_id=token_id,
            count=read.count,
            record=read.record,
            robot_id=read.robot_id,
            topic=read.topic or "",
        )
        for read in reads
    ]
    return {row.record_owner_id: row.pk for row in Access.objects.bulk_create(rows)}


def _shared(values: set[Any]) -> Any:
    return next(iter(values)) if len(values) == 1 else None


def _records_check(
    records: Sequence[Record], viewer: Owner, reads: _ChainReads
) -> list[tuple[dict[str, object], bytes | None]]:
    """Each record's verdict fields, and the bytes checked when it is verified: access, then
    deleted, then the owner's identity; the envelopes of those left fetched at once, then
    each checked against the chain."""
    checked: list[tuple[dict[str, object], bytes | None] | None] = []
    for record in records:
        grant = reads.grant(record, viewer)
        if grant is None or not _in_scope(grant, record):
            checked.append(({"outcome": Verdict.Outcome.NO_ACCESS}, None))
        elif record.is_deleted:
            checked.append(({"outcome": Verdict.Outcome.DELETED}, None))
        else:
            reads.identify(record.owner)
            checked.append(None)
    to_fetch = [record for record, done in zip(records, checked, strict=True) if done is None]
    fetched = iter(envelopes_fetch(to_fetch))
    anchored = [
        done if done is not None else _anchored_check(record, viewer, reads, next(fetched))
        for record, done in zip(records, checked, strict=True)
    ]
    return _signatures_check(records, anchored, reads)


def _signatures_check(
    records: Sequence[Record],
    anchored: Sequence[tuple[dict[str, object], bytes | None]],
    reads: _ChainReads,
) -> list[tuple[dict[str, object], bytes | None]]:
    """The robot signatures of the records whose envelopes hold against the chain, verified
    all at once on every core (provenance.claims_hold): a record whose signature does not hold
    is refused, and its bytes are not handed on."""
    claims = {
        at: _provenance_claim(record, data, reads)
        for at, (record, (_fields, data)) in enumerate(zip(records, anchored, strict=True))
        if data is not None
    }
    pending = [at for at, claim in claims.items() if isinstance(claim, provenance.SignatureClaim)]
    verified = provenance.claims_hold([claims[at] for at in pending])
    holds = {**claims, **dict(zip(pending, verified, strict=True))}
    checked = []
    for at, (record, (fields, data)) in enumerate(zip(records, anchored, strict=True)):
        if data is not None and not holds[at]:
            security_log.error(
                "record %s is anchored but its robot signature does not hold (signer %r)",
                record.pk,
                record.signer,
            )
            fields, data = {**fields, "outcome": Verdict.Outcome.SIGNATURE_REFUSED}, None
        checked.append((fields, data))
    return checked


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


def _provenance_claim(
    record: Record, data: bytes, reads: _ChainReads
) -> provenance.SignatureClaim | bool:
    """DESIGN.md "Provenance": the anchored envelope names the signer the record was stored
    with; a signed record's key is its owner's on chain (robotKeyOf), added at or before the
    record's anchoring block and not revoked by then, hashes to `signer`, and its signature
    holds over the decrypted content: the signature left to verify (a SignatureClaim), or
    whether the record holds without one. An unsigned record (a robot added by hand) holds as
    unsigned: pages and answers say so, never "genuine"."""
    if not record.signer:
        return not envelope.read_header(data).header.get("signer", "")
    try:
        header, plaintext = envelope.open(reads.keys.of(record), data)
    except (CryptoError, OwnerKey.DoesNotExist):  # anchored, yet not an envelope of its key
        return False
    reads.opened[record.pk] = header, plaintext
    on_chain = reads.robot_key_of(record.signer)
    public_key = record.robot.public_key
    if not (
        header.get("signer", "") == record.signer
        and on_chain.owner is not None
        and on_chain.owner.lower() == record.owner.eoa_address.lower()
        and record.block_number is not None
        and on_chain.live_at(record.block_number)
        and public_key
    ):
        return False
    try:
        return provenance.signature_claim(public_key, header, plaintext)
    except SignatureInvalid:
        return False


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
    record: Record,
    viewer: Owner,
    reads: _ChainReads,
    fetched: tuple[bytes, str] | FileNotFoundError,
) -> tuple[dict[str, object], bytes | None]:
    """The stored envelope's SM3 digest against the chain's: the verdict's fields, and the
    bytes checked when they match."""
    if isinstance(fetched, FileNotFoundError):
        if Record.objects.filter(pk=record.pk, deleted_at__isnull=False).exists():
            # Deleted while this check ran: its ciphertext was removed on purpose.
            return {"outcome": Verdict.Outcome.DELETED, "source": "storage"}, None
        # The durable copy is gone, removed behind the portal's back: nothing is left that
        # hashes to the digest the chain holds.
        _record_tampered(record, viewer, source="storage", computed="missing", chain="")
        return {"outcome": Verdict.Outcome.TAMPERED, "source": "storage"}, None
    data, source = fetched
    computed = sm3.sm3_hex(data)
    if record.anchor_root_id is not None:
        return _proof_check(record, viewer, reads, data=data, source=source, computed=computed)
    on_chain = reads.client.data_query(record.id, owner=record.owner.eoa_address)
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
    reads: _ChainReads,
    *,
    data: bytes,
    source: str,
    computed: str,
) -> tuple[dict[str, object], bytes | None]:
    """Root mode: the record's leaf (owner, id, the stored envelope's SM3) folded up its audit
    path must give its tree's root, which the owner's account anchored with the same size:
    one eth_call (rootOf) per tree in a run, no per-record storage on chain."""
    tree = record.anchor_root
    fields = {"computed_digest": computed, "source": source}
    on_chain = reads.root_of(tree.sender, tree.root)
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


# The verdict's fields the worker hands back, so that the web process needs no read of them.
_ANSWERED = ("outcome", "computed_digest", "chain_digest", "source", "block_number")


def verification_answer(verification: Verification) -> dict[str, Any]:
    """What the worker hands back to the view (JSON through the result backend)."""
    verdict, data = verification.verdict, verification.envelope
    return {
        "record_id": str(verdict.record_id),
        "verdict_id": verdict.pk,
        **{name: getattr(verdict, name) for name in _ANSWERED},
        "created_at": verdict.created_at.isoformat(),
        "envelope": base64.b64encode(data).decode("ascii") if data is not None else None,
    }


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


def record_open(
    *,
    record_id: uuid.UUID | str,
    viewer: Owner,
    credential: str = Verdict.Credential.UNKNOWN,
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
    (per record owner) in the access log, the records sent in batches of VERIFY_BATCH all at
    once, the keys unwrapped while the worker checks. A read of one batch (a record's page,
    a page of records) is sent at once and its Access opened by the worker with the verdicts,
    in one commit, and coalesced as a refused view is; a read of several batches has its
    Access opened here first, so that every batch's verdicts point to it. One result per
    record, in order: the opened record, or the SharingError that refuses it
    (VerificationUnavailable for each of a batch the worker could not answer). `credential`
    (and `token`, an owner API token's) is the viewer's credential that asked.
    IdentityMismatch is raised as the worker raised it."""
    token_id = _token_id(token)
    _credential_check(credential, token_id)
    if not records:
        return []
    batches = [records[at : at + VERIFY_BATCH] for at in range(0, len(records), VERIFY_BATCH)]
    sent_accesses = None
    if len(batches) > 1:
        accesses = accesses_open(
            kind=kind,
            viewer_id=viewer.pk,
            records=records,
            credential=credential,
            token_id=token_id,
        )
        sent_accesses = {str(owner_id): access_id for owner_id, access_id in accesses.items()}
    pending = [
        _send(
            VERIFY_TASK,
            [str(record.pk) for record in batch],
            viewer.pk,
            credential,
            token_id,
            sent_accesses,
            kind,
        )
        for batch in batches
    ]
    keys = RecordKeys()
    keys.warm(records)  # while the worker checks
    results: list[OpenedRecord | SharingError] = []
    for batch, sent in zip(batches, pending, strict=True):
        try:
            answers = _await_answer(sent, f"{len(batch)} records", viewer)
        except VerificationUnavailable as exc:
            results += [VerificationUnavailable(str(exc)) for _ in batch]
            continue
        by_record = {answer["record_id"]: answer for answer in answers}
        for record in batch:
            answer = by_record.get(str(record.pk))
            try:
                if answer is None:  # gone meanwhile
                    raise RecordNotFound(NOT_VISIBLE)
                verdict = _verdict_of(answer, record, viewer)
                results.append(_decrypted(record, verdict, _envelope_of(answer), keys))
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


def _verdict_of(answer: dict[str, Any], record: Record, viewer: Owner) -> Verdict:
    """The verdict the worker wrote, as it answered it (not read back)."""
    return Verdict(
        pk=answer["verdict_id"],
        record=record,
        viewer=viewer,
        record_owner_id=record.owner_id,
        created_at=datetime.fromisoformat(answer["created_at"]),
        **{name: answer[name] for name in _ANSWERED},
    )


def record_key(record: Record) -> bytes:
    """The SM4 key the record was sealed under."""
    key = owner_key_by_id(record.owner, record.key_id)
    if key is None:
        raise OwnerKey.DoesNotExist(f"no key {record.key_id} of the record's owner")
    return owner_key_bytes(key)


class RecordKeys:
    """The SM4 keys of records, unwrapped once per (owner, key id) for a read or an export."""

    def __init__(self) -> None:
        self._keys: dict[tuple[int, str], bytes] = {}

    def of(self, record: Record) -> bytes:
        wanted = (record.owner_id, record.key_id)
        if wanted not in self._keys:
            self._keys[wanted] = record_key(record)
        return self._keys[wanted]

    def warm(self, records: Sequence[Record]) -> None:
        """Unwrap the records' keys now; one that fails is reported where a record that may
        be shown is opened (the check's verdict comes first)."""
        for record in records:
            with suppress(OwnerKey.DoesNotExist):
                self.of(record)


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
    return OpenedRecord(record, verdict, header, plaintext, data)


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
