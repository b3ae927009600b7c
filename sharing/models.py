"""Records (envelopes anchored on chain), grants between owners, and integrity verdicts."""

import uuid

from django.conf import settings
from django.db import models

from accounts.models import Owner, OwnerToken, Robot


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


class Record(models.Model):
    """One envelope: its bytes live in durable storage, its SM3 digest on chain."""

    class Status(models.TextChoices):
        PENDING = "pending", "pending"
        ANCHORED = "anchored", "anchored"
        FAILED = "failed", "failed"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    owner = models.ForeignKey(Owner, on_delete=models.PROTECT, related_name="records")
    robot = models.ForeignKey(Robot, on_delete=models.PROTECT, related_name="records")
    topic = models.CharField(max_length=255)
    data_type = models.CharField(max_length=255)
    seq = models.BigIntegerField()
    captured_at = models.DateTimeField()
    key_id = models.CharField(max_length=16)
    digest = models.CharField(max_length=64, help_text="hex SM3 of the envelope")
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

    class Meta:
        ordering = ["-captured_at"]
        constraints = [
            models.UniqueConstraint(fields=["robot", "seq"], name="record_seq_unique_per_robot"),
        ]
        indexes = [
            models.Index(fields=["status", "created_at"], name="record_status_created"),
            models.Index(fields=["owner", "status"], name="record_owner_status"),
            models.Index(fields=["tx_hash"], name="record_tx_hash"),
        ]

    def __str__(self) -> str:
        return f"{self.owner} {self.topic} #{self.seq}"


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


class Verdict(models.Model):
    """The outcome of one integrity check at view time: the audit trail of who viewed what."""

    class Outcome(models.TextChoices):
        VERIFIED = "verified", "verified"
        TAMPERED = "tampered", "TAMPERED"
        NOT_ANCHORED_YET = "not_anchored_yet", "not anchored yet"
        NO_ACCESS = "no_access", "no access"

    record = models.ForeignKey(Record, on_delete=models.CASCADE, related_name="verdicts")
    viewer = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="verdicts")
    # An operator's check from the admin console, made with the viewer's (the owner's) rights:
    # the audit trail must not show it as the owner viewing their data.
    checked_by = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
        help_text="the operator who ran this check; empty when the viewer viewed the record",
    )
    outcome = models.CharField(max_length=20, choices=Outcome.choices)
    computed_digest = models.CharField(max_length=64, blank=True)
    chain_digest = models.CharField(max_length=64, blank=True)
    source = models.CharField(max_length=16, blank=True, help_text="cache or storage")
    block_number = models.BigIntegerField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]

    def __str__(self) -> str:
        if self.checked_by_id:
            return f"{self.record_id} checked by operator {self.checked_by}: {self.outcome}"
        return f"{self.record_id} viewed by {self.viewer}: {self.outcome}"


class SecurityEvent(models.Model):
    """Something an operator must look at: tampering, a digest that differs on chain."""

    class Kind(models.TextChoices):
        TAMPERED_ON_VIEW = "tampered_on_view", "stored data differs from the chain"
        CHAIN_DIGEST_MISMATCH = "chain_digest_mismatch", "chain holds another digest for the id"
        FORGED_UPLOAD = "forged_upload", "upload refused as forged"
        SEQUENCE_CONFLICT = "sequence_conflict", "a robot's sequence number used for other data"

    kind = models.CharField(max_length=32, choices=Kind.choices)
    record = models.ForeignKey(Record, on_delete=models.SET_NULL, null=True, blank=True)
    owner = models.ForeignKey(Owner, on_delete=models.SET_NULL, null=True, blank=True)
    detail = models.JSONField(default=dict)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]

    def __str__(self) -> str:
        return f"{self.kind} at {self.created_at:%Y-%m-%d %H:%M:%S}"
