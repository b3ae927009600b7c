"""The worker's integrity check (`records_verify`, the task sharing.tasks.records_verify): one
path for any number of records of one viewer, the view of one record being N = 1.

One run reads one chain head, checks access once per record owner (first, so that a viewer
without access learns nothing, not even that a record was deleted: grant_on_chain), the owner's
identity once, then fetches every stored envelope left at once (Redis cache, else durable
storage) and hashes each (SM3) against the chain: one `rootOf` per distinct Merkle root (the
records of one tree share it), `robotKeyOfOwner` once per signer and owner, and every robot
signature verified side by side on every core. Every verdict is written in bulk (an INSERT of
prepared rows per batch the backend takes: core/rows.py) and points to its Access, the line
the owner's access log shows (opened by the web for its reads, else here).
It hands back the bytes it checked, and for a reader in the same process (an export) the
signed envelopes it opened, so that nothing is decrypted twice in one process.
"""

import base64
import logging
import uuid
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from django.db import transaction

from accounts.identity import owner_identity_check
from accounts.models import Owner, OwnerKey, Robot
from chainworker.client import AuthROSChain
from chainworker.codec import OnChainRoot, RobotKeyOnChain
from chainworker.services import chain_client, chain_head
from core.metrics import VERDICTS
from core.rows import FixedInsert, instances_made
from sharing.cache import envelopes_fetch
from sharing.models import Access, Credential, Grant, Record, Verdict
from sharing.selectors.records import records_to_check_by_id
from sharing.services.roots import record_path
from sharing.verification.access import (
    access_kind_check,
    access_refused_again,
    accesses_open,
    credential_check,
)
from sharing.verification.grant_on_chain import grant_checked, grant_covers
from sharing.verification.keys import RecordKeys
from sharing.verification.tamper import record_tampered_respond
from smcrypto import envelope, provenance, sm3
from smcrypto.errors import CryptoError, SignatureInvalid
from smcrypto.merkle import leaf_hash, proof_holds

security_log = logging.getLogger("authros.security")

# A record's verdict fields and the bytes checked (only when verified).
_Checked = tuple[dict[str, object], bytes | None]


@dataclass(frozen=True)
class Verification:
    verdict: Verdict
    envelope: bytes | None  # the bytes that were checked; only when verified
    # Those bytes opened (header, plaintext), when the check decrypted them for the robot
    # signature (a signed record's); for a reader in the same process to use, never sent.
    opened: tuple[dict, bytes] | None = None


class _ChainReads:
    """What one run of checks reads from the chain, each asked once in the run: the grant per
    record owner, the owner's identity, `rootOf` per tree and `robotKeyOfOwner` per signer and
    record owner; and
    the records' keys (to check a signature over the plaintext), unwrapped once per key."""

    def __init__(self, client: AuthROSChain) -> None:
        self.client = client
        self.keys = RecordKeys()
        self.grants: dict[int, Grant | None] = {}
        self.identified: set[int] = set()
        self.roots: dict[tuple[str, str], OnChainRoot | None] = {}
        self.robot_keys: dict[tuple[str, str], RobotKeyOnChain] = {}
        # The signed envelopes the run opened to check their signatures, by record.
        self.opened: dict[uuid.UUID, tuple[dict, bytes]] = {}

    def grant(self, record: Record, viewer: Owner) -> Grant | None:
        if record.owner_id not in self.grants:
            self.grants[record.owner_id] = grant_checked(record, viewer, self.client)
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

    def robot_key_of(self, signer: str, *, owner: str) -> RobotKeyOnChain:
        """The key as `owner` registered it: another owner's registration of it counts for
        nothing (issue 46)."""
        if (owner, signer) not in self.robot_keys:
            self.robot_keys[owner, signer] = self.client.robot_key_of_owner(
                bytes.fromhex(signer), owner=owner
            )
        return self.robot_keys[owner, signer]


def records_verify(
    *,
    record_ids: Sequence[uuid.UUID | str] = (),
    records: Sequence[Record] | None = None,
    viewer_id: int,
    credential: str = Credential.UNKNOWN,
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
    Every check leaves a Verdict (the trail of what each check found, and the chain's head
    then, as last seen by the portal), all in one INSERT, each pointing to its Access:
    `accesses` (record owner id -> Access id) when the web process opened them for its read,
    else opened here, of `kind` (by default a view of one record, a page of several, an
    operator's check). `checked_by_id` names the operator running the check with the viewer's
    rights (the admin console's re-verify), recorded as `operator`, never as the viewer's own
    view; `credential` and `token_id` say which credential of the viewer asked. `records`,
    instead of `record_ids`: the records already read with their owner, robot and tree (an
    export's batch), checked as they are, not read again. A read refused whole, as the
    viewer's last one of the same owner's records was, is answered as that one and not
    written again (access_refused_again).
    """
    if checked_by_id is not None:
        credential, token_id = Credential.OPERATOR, None
    credential_check(credential, token_id)
    if records is None:
        records = _records_read(record_ids)
    kind = kind or _kind_of(len(records), checked_by_id)
    access_kind_check(kind)
    viewer = Owner.objects.get(pk=viewer_id)
    reads = _ChainReads(chain_client())
    block = chain_head(reads.client)
    checked = _records_check(records, viewer, reads)
    with transaction.atomic():  # the access line and its verdicts: one commit
        again = None
        if checked_by_id is None:
            outcomes = [fields["outcome"] for fields, _data in checked]
            again = access_refused_again(records, outcomes, viewer, kind=kind, accesses=accesses)
        if again is not None:  # answered as the refused read before it, not written again
            return [Verification(again, None) for _ in records]
        if accesses is None:  # opened once the checks ran: a check that raised leaves no line
            accesses = accesses_open(
                kind=kind,
                viewer_id=viewer_id,
                records=records,
                credential=credential,
                token_id=token_id,
                checked_by_id=checked_by_id,
            )
        verdicts = _verdicts_new(
            records,
            [
                {
                    "access_id": accesses[record.owner_id],
                    "block_number": _verdict_block(block, record),
                    **fields,
                }
                for record, (fields, _data) in zip(records, checked, strict=True)
            ],
        )
        _VERDICTS.insert(verdicts)
    for outcome, count in Counter(verdict.outcome for verdict in verdicts).items():
        VERDICTS.labels(outcome).inc(count)  # where they are written: any task, or a direct check
    return [
        Verification(verdict, data, reads.opened.get(verdict.record_id) if data else None)
        for verdict, (_fields, data) in zip(verdicts, checked, strict=True)
    ]


# A check's verdicts in one INSERT per batch the backend takes, its SQL written once: the ORM's
# per-object work in bulk_create was the largest part of a series' check (bench/REPORT.md).
_VERDICTS = FixedInsert(Verdict)


# Verdict's columns in the model's order: a check makes a verdict per record, from its values
# in order (core.rows.instances_made, without Model.__init__'s per-field work), its record
# cached on it.
_VERDICT_COLUMNS = [(field.attname, field.get_default) for field in Verdict._meta.concrete_fields]
_VERDICT_NAMES = [name for name, _default in _VERDICT_COLUMNS]
_VERDICT_RECORD = Verdict._meta.get_field("record")


def _verdicts_new(records: Sequence[Record], values: Sequence[dict[str, object]]) -> list[Verdict]:
    """A new verdict of each record with its column values (by attname), the others their
    defaults."""
    rows = []
    for record, given in zip(records, values, strict=True):
        given = {**given, "record_id": record.pk}
        rows.append(
            [given[name] if name in given else default() for name, default in _VERDICT_COLUMNS]
        )
    verdicts = instances_made(Verdict, _VERDICT_NAMES, rows, alias=None)
    for verdict, record in zip(verdicts, records, strict=True):
        _VERDICT_RECORD.set_cached_value(verdict, record)
    return verdicts


def _records_read(record_ids: Sequence[uuid.UUID | str]) -> list[Record]:
    """The records of these ids that exist, in the order asked, with what the check reads."""
    return records_to_check_by_id([uuid.UUID(str(record_id)) for record_id in record_ids])


def _kind_of(count: int, checked_by_id: int | None) -> str:
    if checked_by_id is not None:
        return Access.Kind.CHECK
    return Access.Kind.VIEW if count == 1 else Access.Kind.PAGE


def _records_check(records: Sequence[Record], viewer: Owner, reads: _ChainReads) -> list[_Checked]:
    """Each record's verdict fields, and the bytes checked when it is verified: access, then
    deleted, then the owner's identity; the envelopes of those left fetched at once, then
    each checked against the chain."""
    checked: list[_Checked | None] = []
    for record in records:
        grant = reads.grant(record, viewer)
        if grant is None or not grant_covers(grant, record):
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
    records: Sequence[Record], anchored: Sequence[_Checked], reads: _ChainReads
) -> list[_Checked]:
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


def _verdict_block(head: int, record: Record) -> int:
    """The block a verdict states: the chain's head as the portal last saw it, never below the
    block the record was anchored in (which the chain answering for it must have)."""
    return max(head, record.block_number or 0)


def robot_signs(robot: Robot) -> bool:
    """Whether every record of the robot must carry its signature: a paired robot's always.

    Read from the robot, never from the record's row (its `signer` column says what the upload
    stored, and whoever can write a row can blank it). A robot is paired from its making: an
    approved pairing makes a new Robot with its key (accounts.services.pairing), and nothing
    gives a key to a robot added by hand later, so a robot with a key has signed every record
    it ever uploaded. Not decided from the chain: the one exception, records stored unsigned
    by a robot paired before robots signed (accounts migration 0008 gave such robots their
    key's hash), is refused too, because a rule "unsigned is fine if anchored before the key
    reached the chain" would let whoever runs the portal, who sends that key's registration,
    hold it back and anchor unsigned records meanwhile."""
    return bool(robot.key_hash or robot.public_key)


def _provenance_claim(
    record: Record, data: bytes, reads: _ChainReads
) -> provenance.SignatureClaim | bool:
    """DESIGN.md "Provenance" (v1) and "Provenance v2": a paired robot's record (robot_signs)
    must be signed, its anchored envelope naming the robot's own key; that key is its owner's
    on chain (robotKeyOfOwner), added at or before the record's anchoring block and not revoked by
    then, and the signature holds over the decrypted content (v2: the record folds up its
    batch path to the root the batch's signature is over). The signature left to verify (a
    SignatureClaim, equal for the records of one batch, so that claims_hold verifies a batch
    once), or whether the record holds without one. A record of a robot added by hand holds
    as unsigned when its envelope names no signer: pages and answers say so, never "genuine".
    v1 or v2 is the anchored envelope's header's (provenance.signature_claim); nothing here
    reads signedness or format from the record's row, which must agree with the envelope
    (its signer and, for v2, its topic_seq, which the count of records is made from)."""
    robot = record.robot
    if not robot_signs(robot):
        header = envelope.read_header(data).header
        return envelope.provenance_format(header) == "unsigned" and not record.signer
    try:
        header, plaintext = reads.keys.opening(record).open(data)
    except (CryptoError, OwnerKey.DoesNotExist):  # anchored, yet not an envelope of its key
        return False
    reads.opened[record.pk] = header, plaintext
    try:
        signer = robot.key_hash or provenance.key_hash(robot.public_key)
    except CryptoError:  # a public key on record that is not an SM2 point
        return False
    if header.get("signer") != signer or not _row_agrees(record, header):
        return False  # unsigned (the audit's record written under a paired robot), or not its
    on_chain = reads.robot_key_of(signer, owner=record.owner.eoa_address)
    if not (
        on_chain.owner is not None
        and on_chain.owner.lower() == record.owner.eoa_address.lower()
        and record.block_number is not None
        and on_chain.live_at(record.block_number)
        and robot.public_key
    ):
        return False
    try:
        return provenance.signature_claim(robot.public_key, header, plaintext)
    except SignatureInvalid:
        return False


def _row_agrees(record: Record, header: dict) -> bool:
    """Whether the record's row states what its anchored envelope's header says: the signer,
    and for a v2 record the topic_seq under its signature (the completeness answer counts
    rows: a v2 row renumbered or unnumbered is refused). A v1 header numbers nothing, so a
    v1 row's number is not checked here; the ingest stores none."""
    if record.signer != header.get("signer", ""):
        return False
    return envelope.provenance_format(header) != "v2" or record.topic_seq == header["topic_seq"]


def _anchored_check(
    record: Record,
    viewer: Owner,
    reads: _ChainReads,
    fetched: tuple[bytes, str] | FileNotFoundError,
) -> _Checked:
    """The stored envelope's SM3 digest against the chain's: the verdict's fields, and the
    bytes checked when they match."""
    if isinstance(fetched, FileNotFoundError):
        if Record.objects.filter(pk=record.pk, deleted_at__isnull=False).exists():
            # Deleted while this check ran: its ciphertext was removed on purpose.
            return {"outcome": Verdict.Outcome.DELETED, "source": "storage"}, None
        # The durable copy is gone, removed behind the portal's back: nothing is left that
        # hashes to the digest the chain holds.
        record_tampered_respond(
            record=record, viewer=viewer, source="storage", computed="missing", chain=""
        )
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
        record_tampered_respond(
            record=record, viewer=viewer, source=source, computed=computed, chain=chain_digest
        )
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
) -> _Checked:
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
        record_tampered_respond(
            record=record, viewer=viewer, source=source, computed=computed, chain=chain_digest
        )
        return {"outcome": Verdict.Outcome.TAMPERED, **fields}, None
    return {"outcome": Verdict.Outcome.VERIFIED, **fields}, data


# The verdict's fields the worker hands back, so that the web process needs no read of them.
ANSWERED_FIELDS = ("outcome", "computed_digest", "chain_digest", "source", "block_number")


def verification_answer(verification: Verification) -> dict[str, Any]:
    """What the worker hands back to the view (JSON through the result backend)."""
    verdict, data = verification.verdict, verification.envelope
    return {
        "record_id": str(verdict.record_id),
        "verdict_id": verdict.pk,
        **{name: getattr(verdict, name) for name in ANSWERED_FIELDS},
        "created_at": verdict.created_at.isoformat(),
        "envelope": base64.b64encode(data).decode("ascii") if data is not None else None,
    }
