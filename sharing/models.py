"""Records (envelopes anchored on chain), grants between owners, the access log (`Access`, one
line per read, with its records' integrity verdicts), exports."""

import uuid

from django.conf import settings
from django.db import models
from django.utils import timezone

from accounts.models import Owner, OwnerToken, Robot
from sharing.scope import expiry_seconds, scope_commitment
from sharing.selection import RecordSelection


class AnchorRoot(models.Model):
    """A Merkle tree of one owner's records (smcrypto.merkle), its root anchored by the
    owner's EOA with anchorRoot; roots of one sender are chained by prev_root on chain."""

    class Status(models.TextChoices):
        SENT = "sent", "sent"  # built and sent (or about to be): may still land
        ANCHORED = "anchored", "anchored"
        DROPPED = "dropped", "dropped"  # can never land: its records went into another tree

    owner = models.ForeignKey(Owner, on_delete=models.PROTECT, related_name="anchor_roots")
    sender = models.CharField(max_length=42, help_text="the EOA that anchors it")
    root = models.CharField(max_length=64, help_text="hex SM3 Merkle root")
    prev_root = models.CharField(max_length=64, help_text="the sender's root before it")
    size = models.PositiveIntegerField()
    # The records' ids (16 bytes each) in leaf order: the tree can be rebuilt from these.
    leaves = models.BinaryField()
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.SENT)
    tx_hash = models.CharField(max_length=66, blank=True)
    block_number = models.BigIntegerField(null=True, blank=True)
    anchored_at = models.DateTimeField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]
        constraints = [
            # A dropped tree's records may form the same tree again, after another root.
            models.UniqueConstraint(
                fields=["sender", "root"],
                condition=~models.Q(status="dropped"),
                name="anchor_root_unique",
            ),
        ]
        indexes = [models.Index(fields=["owner", "status"], name="anchor_root_owner_status")]

    def __str__(self) -> str:
        return f"{self.owner} root {self.root[:12]} ({self.size}, {self.status})"


class RecordQuerySet(models.QuerySet):
    def live(self) -> "RecordQuerySet":
        """The records not deleted: a tombstone (deleted_at set) keeps its row, digest and proof,
        but is no record anyone lists, opens or exports."""
        return self.filter(deleted_at__isnull=True)


class Record(models.Model):
    """One envelope: its bytes live in durable storage, its SM3 digest on chain."""

    class Status(models.TextChoices):
        PENDING = "pending", "pending"
        ANCHORED = "anchored", "anchored"
        FAILED = "failed", "failed"

    class Deletion(models.TextChoices):
        """Why a record was deleted."""

        OWNER = "owner", "deleted by its owner"
        RETENTION = "retention", "deleted by the robot's retention policy"
        ACCOUNT = "account", "deleted with its owner's account"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    owner = models.ForeignKey(Owner, on_delete=models.PROTECT, related_name="records")
    robot = models.ForeignKey(Robot, on_delete=models.PROTECT, related_name="records")
    topic = models.CharField(max_length=255)
    data_type = models.CharField(max_length=255)
    seq = models.BigIntegerField()
    captured_at = models.DateTimeField()
    key_id = models.CharField(max_length=16)
    digest = models.CharField(max_length=64, help_text="hex SM3 of the envelope")
    # The robot key that signed the envelope (its `signer` header: SM3 of the robot's SM2 public
    # key, hex), checked at upload; blank for an unsigned record (a robot added by hand).
    signer = models.CharField(max_length=64, blank=True)
    # Provenance v2 (DESIGN.md): the record's place in its signer's count of the topic, under
    # the robot's batch signature; null for a v1 or unsigned record. A (signer, topic,
    # topic_seq) is stored once, ever: tombstones keep theirs, so a gap names its reason.
    topic_seq = models.BigIntegerField(null=True, blank=True)
    size = models.PositiveIntegerField()
    storage_name = models.CharField(max_length=255)
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.PENDING)
    tx_hash = models.CharField(max_length=66, blank=True)
    block_number = models.BigIntegerField(null=True, blank=True)
    anchored_at = models.DateTimeField(null=True, blank=True)
    anchor_attempts = models.PositiveIntegerField(default=0)
    failure_reason = models.CharField(max_length=300, blank=True)
    tampered_at = models.DateTimeField(null=True, blank=True)
    # Anchoring by Merkle root (ANCHOR_MODE=root): the tree the record is in (while pending:
    # the tree in flight), its leaf index and audit path (32-byte hashes, leaf up).
    anchor_root = models.ForeignKey(
        AnchorRoot, on_delete=models.PROTECT, null=True, blank=True, related_name="records"
    )
    leaf_index = models.PositiveIntegerField(null=True, blank=True)
    merkle_path = models.BinaryField(default=b"", blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    # Deletion (sharing/services/deletion.py): the row stays as a tombstone with its digest and
    # proof; the ciphertext is removed from storage and cache, then `purged_at` is set.
    deleted_at = models.DateTimeField(null=True, blank=True)
    deleted_by = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
        help_text="who deleted it; empty when the robot's retention policy did",
    )
    deletion_reason = models.CharField(max_length=16, choices=Deletion.choices, blank=True)
    purged_at = models.DateTimeField(
        null=True, blank=True, help_text="when its ciphertext left storage and cache"
    )

    objects = RecordQuerySet.as_manager()

    class Meta:
        ordering = ["-captured_at"]
        constraints = [
            models.UniqueConstraint(fields=["robot", "seq"], name="record_seq_unique_per_robot"),
            # Also the completeness answer's index: a stream's records in count order.
            models.UniqueConstraint(
                fields=["signer", "topic", "topic_seq"],
                condition=models.Q(topic_seq__isnull=False),
                name="record_topic_seq_unique_per_signer",
            ),
        ]
        indexes = [
            models.Index(fields=["status", "created_at"], name="record_status_created"),
            models.Index(fields=["owner", "status"], name="record_owner_status"),
            models.Index(fields=["tx_hash"], name="record_tx_hash"),
            # The record pages: a list in capture order, a topic's range (plot, gallery), and
            # the dashboard's count of tampered records.
            models.Index(fields=["owner", "captured_at", "seq"], name="record_owner_captured"),
            models.Index(
                fields=["owner", "topic", "data_type", "captured_at"],
                name="record_owner_topic_captured",
            ),
            models.Index(
                fields=["owner"],
                condition=models.Q(tampered_at__isnull=False),
                name="record_owner_tampered",
            ),
            # Retention (a robot's oldest records first), and the robot page's messages per
            # topic over the last hour: the topic and type in the index, so that count reads
            # the index alone (sharing/robot_status.py).
            models.Index(
                fields=["robot", "captured_at", "topic", "data_type"],
                name="record_robot_captured_topic",
            ),
            # The robot page's newest pose and image: one seek per ROS type.
            models.Index(
                fields=["robot", "data_type", "captured_at"], name="record_robot_type_captured"
            ),
            # Tombstones whose ciphertext is still to be removed.
            models.Index(
                fields=["deleted_at"],
                condition=models.Q(deleted_at__isnull=False, purged_at__isnull=True),
                name="record_purge_pending",
            ),
        ]

    def __str__(self) -> str:
        return f"{self.owner} {self.topic} #{self.seq}"

    @property
    def is_deleted(self) -> bool:
        return self.deleted_at is not None


class Grant(models.Model):
    """`owner` lets `grantee` read its records; mirrored by authorityGrant/Revoke on chain."""

    class Status(models.TextChoices):
        PENDING = "pending", "grant pending on chain"
        ACTIVE = "active", "active"
        REVOKING = "revoking", "revocation pending on chain"
        REVOKED = "revoked", "revoked"
        FAILED = "failed", "failed"

    LIVE = (Status.PENDING, Status.ACTIVE, Status.REVOKING)

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="grants_given")
    grantee = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="grants_received")
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.PENDING)
    grant_tx = models.CharField(max_length=66, blank=True)
    grant_block = models.BigIntegerField(null=True, blank=True)
    revoke_tx = models.CharField(max_length=66, blank=True)
    revoke_block = models.BigIntegerField(null=True, blank=True)
    failure_reason = models.CharField(max_length=300, blank=True)
    # Which credential made the grant: "session", "token", or "cli"; with the token if one.
    made_with = models.CharField(max_length=16, default="session")
    made_with_token = models.ForeignKey(
        OwnerToken, on_delete=models.SET_NULL, null=True, blank=True, related_name="grants_made"
    )
    # The scope (sharing/scope.py): robot ids and topics (empty: all) and a capture-time
    # window [since, until); on chain as its SM3 commitment. None of them: all records.
    scope_robots = models.JSONField(default=list, blank=True)
    scope_topics = models.JSONField(default=list, blank=True)
    scope_since = models.DateTimeField(null=True, blank=True)
    scope_until = models.DateTimeField(null=True, blank=True)
    # From then on the grant gives no access, in the portal and on chain (whole seconds).
    expires_at = models.DateTimeField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        ordering = ["-created_at"]
        constraints = [
            models.UniqueConstraint(
                fields=["owner", "grantee"],
                condition=models.Q(status__in=["pending", "active", "revoking"]),
                name="one_live_grant_per_pair",
            ),
        ]

    def __str__(self) -> str:
        return f"{self.owner} -> {self.grantee} ({self.status})"

    @property
    def scope(self) -> RecordSelection:
        return RecordSelection(
            robots=tuple(uuid.UUID(robot) for robot in self.scope_robots),
            topics=tuple(self.scope_topics),
            since=self.scope_since,
            until=self.scope_until,
        )

    @property
    def scope_commitment_hex(self) -> str:
        return scope_commitment(self.scope).hex()

    @property
    def expiry(self) -> int:
        """The expiry as the chain holds it: unix seconds, 0 for never."""
        return expiry_seconds(self.expires_at)

    @property
    def is_expired(self) -> bool:
        return self.expires_at is not None and self.expires_at <= timezone.now()

    @property
    def is_limited(self) -> bool:
        """Scoped or expiring: not the plain all-records grant of authorityGrant."""
        return self.expires_at is not None or not self.scope.is_all

    @property
    def shown_status(self) -> str:
        """The status both sides' pages show: "expired" for a live grant past its expiry."""
        if self.is_expired and self.status in (self.Status.ACTIVE, self.Status.PENDING):
            return "expired"
        return self.status

    @property
    def shown_status_display(self) -> str:
        return "expired" if self.shown_status == "expired" else self.get_status_display()


class GrantChange(models.Model):
    """One change to a grant (made, terms changed, revoked) and the credential that made it:
    the owner's browser session, one of the owner's API tokens, or an operator's command. The
    terms before and after let a revoked token's changes be undone (docs/grants.md)."""

    class Kind(models.TextChoices):
        CREATED = "created", "access given"
        CHANGED = "changed", "terms changed"
        REVOKED = "revoked", "access revoked"

    grant = models.ForeignKey(Grant, on_delete=models.CASCADE, related_name="changes")
    kind = models.CharField(max_length=16, choices=Kind.choices)
    # "session", "token" or "cli" (sharing.services.grants.GRANT_MADE_WITH), with the token if one.
    made_with = models.CharField(max_length=16)
    token = models.ForeignKey(
        OwnerToken,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="grant_changes",
    )
    # The grant's terms before and after (GrantTerms.as_json); null before its creation and
    # after its revocation.
    terms_before = models.JSONField(null=True, blank=True)
    terms_after = models.JSONField(null=True, blank=True)
    created_at = models.DateTimeField(default=timezone.now)

    class Meta:
        ordering = ["-created_at", "-id"]
        indexes = [models.Index(fields=["token", "-created_at"], name="grant_change_by_token")]

    def __str__(self) -> str:
        return f"{self.grant} {self.kind} with {self.made_with}"


class Credential(models.TextChoices):
    """Which credential of the viewer asked: the access log's "from which credential"."""

    UNKNOWN = "", "not recorded"
    SESSION = "session", "browser session"
    TOKEN = "token", "owner API token"
    OPERATOR = "operator", "operator check in the admin"


class Access(models.Model):
    """One access to records, as the owner's access log lists it: a record page or a content
    answer (one record), a page of a gallery, a plot, an export, an operator's check; how many
    records it read, and with which credential. Its records' integrity verdicts point to it:
    they stay the trail of every check, this is the line a person reads. One row per record
    owner the access read records of, so that each owner's log is one indexed range."""

    class Kind(models.TextChoices):
        VIEW = "view", "view"
        PAGE = "page", "page"
        PLOT = "plot", "plot"
        EXPORT = "export", "export"
        CHECK = "check", "operator check"

    kind = models.CharField(max_length=16, choices=Kind.choices)
    viewer = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="accesses")
    record_owner = models.ForeignKey(
        Owner, on_delete=models.CASCADE, related_name="accesses_received"
    )
    checked_by = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
        help_text="the operator who ran this check; empty when the viewer viewed the records",
    )
    credential = models.CharField(
        max_length=16, choices=Credential.choices, blank=True, default=Credential.UNKNOWN
    )
    token = models.ForeignKey(
        OwnerToken, on_delete=models.SET_NULL, null=True, blank=True, related_name="accesses"
    )
    count = models.PositiveIntegerField(help_text="records of the owner this access read")
    # The record when it read one; the robot and topic when all its records share them.
    record = models.ForeignKey(
        Record, on_delete=models.SET_NULL, null=True, blank=True, related_name="+"
    )
    robot = models.ForeignKey(
        Robot, on_delete=models.SET_NULL, null=True, blank=True, related_name="+"
    )
    topic = models.CharField(max_length=255, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [
            models.Index(fields=["record_owner", "-created_at", "-id"], name="access_owner_time"),
            models.Index(fields=["viewer", "-created_at", "-id"], name="access_viewer_time"),
        ]

    def __str__(self) -> str:
        return f"{self.kind} of {self.count} record(s) of {self.record_owner} by {self.viewer}"


class Verdict(models.Model):
    """The outcome of one record's integrity check at view time: the trail under its Access,
    which says who read it, when and with which credential (the one access log)."""

    class Outcome(models.TextChoices):
        VERIFIED = "verified", "verified"
        TAMPERED = "tampered", "TAMPERED"
        NOT_ANCHORED_YET = "not_anchored_yet", "not anchored yet"
        NO_ACCESS = "no_access", "no access"
        # The record was deleted (its ciphertext removed) while the check ran.
        DELETED = "deleted", "deleted"
        # Its envelope is the anchored one, but the robot key it names is not its owner's
        # registered key on chain at its anchoring (or was revoked before it): not genuine.
        SIGNATURE_REFUSED = "signature_refused", "signature not valid"

    record = models.ForeignKey(Record, on_delete=models.CASCADE, related_name="verdicts")
    # The access (a view, a page, a plot...) the check was made for: its viewer, record owner,
    # credential, token and operator are the verdict's.
    access = models.ForeignKey(Access, on_delete=models.CASCADE, related_name="verdicts")
    outcome = models.CharField(max_length=20, choices=Outcome.choices)
    computed_digest = models.CharField(max_length=64, blank=True)
    chain_digest = models.CharField(max_length=64, blank=True)
    source = models.CharField(max_length=16, blank=True, help_text="cache or storage")
    block_number = models.BigIntegerField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]

    def __str__(self) -> str:
        access = self.access
        if access.checked_by_id:
            return f"{self.record_id} checked by operator {access.checked_by}: {self.outcome}"
        return f"{self.record_id} viewed by {access.viewer}: {self.outcome}"


class SecurityEvent(models.Model):
    """Something an operator must look at: tampering, a digest that differs on chain."""

    class Kind(models.TextChoices):
        TAMPERED_ON_VIEW = "tampered_on_view", "stored data differs from the chain"
        CHAIN_DIGEST_MISMATCH = "chain_digest_mismatch", "chain holds another digest for the id"
        FORGED_UPLOAD = "forged_upload", "upload refused as forged"
        SEQUENCE_CONFLICT = "sequence_conflict", "a robot's sequence number used for other data"
        # DESIGN.md "Provenance": a paired robot's upload must be signed by its own live key.
        UNSIGNED_UPLOAD = "unsigned_upload", "a paired robot's upload without a signature"
        FOREIGN_SIGNER = "foreign_signer", "upload signed by a key that is not the robot's"
        BAD_SIGNATURE = "bad_signature", "upload whose signature does not match its content"
        # DESIGN.md "Provenance v2": a (signer, topic, topic_seq) is used once, ever.
        TOPIC_SEQ_REUSED = (
            "topic_seq_reused",
            "a robot's record number on a topic (topic_seq) used again",
        )
        # Issue 46: a robot key is its registering owner's; another owner claiming it is told.
        ROBOT_KEY_DISPUTED = (
            "robot_key_disputed",
            "a robot's key claimed by another owner, in a pairing or on chain",
        )

    kind = models.CharField(max_length=32, choices=Kind.choices)
    record = models.ForeignKey(Record, on_delete=models.SET_NULL, null=True, blank=True)
    owner = models.ForeignKey(Owner, on_delete=models.SET_NULL, null=True, blank=True)
    detail = models.JSONField(default=dict)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]

    def __str__(self) -> str:
        return f"{self.kind} at {self.created_at:%Y-%m-%d %H:%M:%S}"


class Export(models.Model):
    """An export of the verified records of a selection: an MCAP file and its proof bundle,
    made by a worker, kept sealed in the envelope storage (SM4-GCM under `key_wrapped`, a key
    of its own wrapped under the KEK) until `expires_at`, for its requester only, and only
    while the requester may still view every record in it (else `withdrawn`, with why)."""

    class Status(models.TextChoices):
        QUEUED = "queued", "queued"
        RUNNING = "running", "running"
        DONE = "done", "ready"
        FAILED = "failed", "failed"
        EXPIRED = "expired", "expired"
        WITHDRAWN = "withdrawn", "withdrawn"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    requester = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="exports")
    # The credential that asked for it, as its access-log lines record it.
    credential = models.CharField(
        max_length=10, choices=Credential.choices, blank=True, default=Credential.UNKNOWN
    )
    token = models.ForeignKey(
        OwnerToken, on_delete=models.SET_NULL, null=True, blank=True, related_name="exports"
    )
    # {"robots": [uuid...], "topics": [...], "since": iso or null, "until": iso or null}
    selection = models.JSONField(default=dict)
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.QUEUED)
    total = models.PositiveIntegerField(default=0, help_text="records selected")
    processed = models.PositiveIntegerField(default=0, help_text="records checked so far")
    exported = models.PositiveIntegerField(default=0)
    # [{"record", "topic", "captured_at", "reason"}]: the records left out, and why.
    excluded = models.JSONField(default=list, blank=True)
    mcap_name = models.CharField(max_length=255, blank=True)
    bundle_name = models.CharField(max_length=255, blank=True)
    mcap_size = models.PositiveBigIntegerField(default=0)
    bundle_size = models.PositiveBigIntegerField(default=0)
    mcap_sm3 = models.CharField(max_length=64, blank=True)
    # The files' key (SM4), wrapped under the KEK for this export only; emptied when its
    # files are removed, so that a copy of them (a backup) no longer opens either.
    key_wrapped = models.BinaryField(default=b"", blank=True)
    # The chain the bundle's records are anchored on, for the verify command shown.
    chain_id = models.BigIntegerField(null=True, blank=True)
    contract = models.CharField(max_length=42, blank=True)
    error = models.CharField(max_length=300, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    finished_at = models.DateTimeField(null=True, blank=True)
    expires_at = models.DateTimeField()

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["status", "expires_at"], name="export_status_expiry")]

    def __str__(self) -> str:
        return f"export {self.pk} by {self.requester} ({self.status})"

    @property
    def percent(self) -> int:
        """How far it is, in percent of the records checked."""
        if self.status == self.Status.DONE:
            return 100
        return int(100 * self.processed / self.total) if self.total else 0

    @property
    def finished(self) -> bool:
        return self.status not in (self.Status.QUEUED, self.Status.RUNNING)


class ExportRecord(models.Model):
    """A record inside a done export's files: what its download checks access and deletion
    against. Removed with the export's files."""

    export = models.ForeignKey(Export, on_delete=models.CASCADE, related_name="contents")
    record = models.ForeignKey(Record, on_delete=models.CASCADE, related_name="exported_in")

    class Meta:
        constraints = [
            models.UniqueConstraint(fields=["export", "record"], name="one_export_record"),
        ]

    def __str__(self) -> str:
        return f"record {self.record_id} in export {self.export_id}"
