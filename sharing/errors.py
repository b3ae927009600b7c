"""What the sharing services refuse. `http_status` is the one mapping to HTTP codes."""

from typing import Any

from core.errors import DomainError


class SharingError(DomainError):
    code = "sharing_error"
    http_status = 400


class ViewRefused(SharingError):
    """A view of a record's content refused after its check: the record and the verdict the
    check left ride along, so that whoever shows the refusal need not look them up again."""

    def __init__(self, message: str, *, record: Any = None, verdict: Any = None) -> None:
        super().__init__(message)
        self.record = record
        self.verdict = verdict


class InvalidEnvelope(SharingError):
    code = "invalid_envelope"


class EnvelopeTooLarge(SharingError):
    code = "envelope_too_large"
    http_status = 413


class HeaderMismatch(SharingError):
    code = "header_mismatch"
    http_status = 403


class UnknownKey(SharingError):
    code = "unknown_key"
    http_status = 403


class ForgedEnvelope(SharingError):
    code = "forged_envelope"
    http_status = 403


class SignatureRefused(SharingError):
    """An upload whose robot signature is missing, names a key that is not the robot's, or does
    not match its content (DESIGN.md "Provenance"): nothing of it is stored."""

    code = "signature_refused"
    http_status = 403


class ReplayedSequence(SharingError):
    """These very envelopes are stored already (a retransmission whose 201 was lost)."""

    code = "replayed_sequence"
    http_status = 409


class SequenceConflict(SharingError):
    """A sequence number this robot used already, for other data (or skipped): a robot that
    lost its state, or someone else uploading with its token and key."""

    code = "sequence_conflict"
    http_status = 409

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.detail = detail or {}


class TopicSeqReused(SharingError):
    """A v2 record's `topic_seq` that its signer and topic used already, for a record stored
    before (tombstones keep theirs) or another of the same upload (DESIGN.md "Provenance v2":
    never reused): a robot that lost its counter, or its key in other hands. Nothing of the
    upload is stored; the owner is told (a SecurityEvent)."""

    code = "topic_seq_reused"
    http_status = 409

    def __init__(self, message: str, *, detail: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.detail = detail or {}


class OwnerNotFound(SharingError):
    code = "owner_not_found"
    http_status = 404


class OwnerAmbiguous(SharingError):
    """The name given is an owner's, but another live owner's name looks the same (made
    before usernames were held apart: accounts.usernames)."""

    code = "owner_ambiguous"
    http_status = 409


class SelfGrant(SharingError):
    code = "self_grant"


class GranteeNotRegistered(SharingError):
    code = "grantee_not_registered"
    http_status = 409


class NotRegisteredYet(SharingError):
    code = "not_registered_yet"
    http_status = 409


class AlreadyGranted(SharingError):
    code = "already_granted"
    http_status = 409


class RevocationPending(SharingError):
    """Access given again while the pair's revocation is still on its way to the chain."""

    code = "revocation_pending"
    http_status = 409


class NoGrant(SharingError):
    code = "no_grant"
    http_status = 404


# The one answer for a record the caller may not see, whether it exists or not (issue 37):
# the same status, code and words, so that an id tells nothing.
NOT_VISIBLE = "no such record, or not shared with you"


class AccessDenied(ViewRefused):
    """The caller may not see the record (no live grant, or outside its scope): answered as
    RecordNotFound is (404 `not_found`, NOT_VISIBLE); the refused view's verdict is kept."""

    code = "not_found"
    http_status = 404


class IntegrityCheckFailed(ViewRefused):
    code = "integrity_check_failed"
    http_status = 409


class NotAnchoredYet(ViewRefused):
    code = "not_anchored_yet"
    http_status = 409


class SeriesRefused(SharingError):
    """A series that cannot be asked for (fields, points, a range too long or too full)."""

    code = "invalid_series"
    http_status = 400


class RecordNotFound(SharingError):
    code = "not_found"
    http_status = 404


class VerificationUnavailable(SharingError):
    """The worker did not answer in time (chain or worker down): nothing is shown."""

    code = "verification_unavailable"
    http_status = 503
    retry_after = 5


class CheckBudgetExceeded(SharingError):
    """A read that would have the workers check more records than the caller's budget holds
    now (CHECK_BUDGET, sharing/verification/budget.py): refused whole, nothing checked and
    nothing charged; `retry_after` says when it would fit."""

    code = "check_budget_exceeded"
    http_status = 429

    def __init__(self, message: str, *, retry_after: int) -> None:
        super().__init__(message)
        self.retry_after = retry_after


class StorageUnavailable(SharingError):
    """The envelope storage did not take an upload's files (a disk, or an S3 server that is
    down or answered other bytes than were sent): nothing is stored, the robot sends again."""

    code = "storage_unavailable"
    http_status = 503
    retry_after = 5


class StorageFull(StorageUnavailable):
    """A disk the portal writes uploads to has less room than STORAGE_MIN_FREE_BYTES: nothing
    is stored, the robot keeps the envelopes in its spool and sends them again later."""

    retry_after = 60


class ExportRefused(SharingError):
    """An export's selection that cannot be exported (nothing in it, too much, a robot the
    requester may not see)."""

    code = "invalid_selection"


class ExportNotFound(SharingError):
    code = "not_found"
    http_status = 404


class RobotNotFound(SharingError):
    """No robot of the caller's with that id: another owner's answers the same."""

    code = "not_found"
    http_status = 404


class ExportNotReady(SharingError):
    code = "export_not_ready"
    http_status = 409


class ExportExpired(SharingError):
    code = "export_expired"
    http_status = 410


class ExportWithdrawn(SharingError):
    """The requester may no longer view every record in the export (a grant revoked, expired
    or narrowed, a record deleted, an account closed): its files are removed, nothing is
    streamed; exporting the selection again takes what they may view now."""

    code = "export_withdrawn"
    http_status = 410


class InvalidGrantTerms(SharingError):
    """A grant's scope or expiry that cannot be granted (a robot not the owner's, a window
    that ends before it starts, an expiry too soon)."""

    code = "invalid_grant_terms"


class RecordDeleted(ViewRefused):
    """The record was deleted: its ciphertext is gone, its row, digest and proof stay."""

    code = "record_deleted"
    http_status = 410


class NotRecordOwner(SharingError):
    """Only a record's owner deletes it; a grantee reads it, nothing more."""

    code = "not_record_owner"
    http_status = 403


class NotDeletableYet(SharingError):
    """A record not anchored yet is not deleted: its tombstone must keep a proof on chain."""

    code = "not_anchored_yet"
    http_status = 409


class TokenCannotWiden(SharingError):
    """An owner API token asked to widen a grant it did not wholly make (docs/grants.md)."""

    code = "token_cannot_widen"
    http_status = 403
