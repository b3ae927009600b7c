"""Owners, their SM4 keys and custodial EOAs, and their robots."""

import uuid

from django.conf import settings
from django.core.exceptions import ValidationError
from django.db import models
from django.utils import timezone

from accounts.agent_config import DEFAULT_TOPICS, InvalidTopics, topics_as_list, topics_parse
from accounts.usernames import username_skeleton


def default_robot_topics() -> list[dict[str, str]]:
    """What a robot records unless told otherwise (also what robots made before topics were
    stored were given)."""
    return topics_as_list(DEFAULT_TOPICS)


def validate_robot_topics(value: object) -> None:
    """A robot's topics: a non-empty list of {name, type}, as the agent's config takes them."""
    try:
        topics_parse(value)
    except InvalidTopics as exc:
        code = "required" if isinstance(value, list) and not value else "invalid_topic"
        raise ValidationError(str(exc), code=code) from None


# The longest retention an owner may set on a robot (a hundred years); None keeps forever.
RETENTION_MAX_DAYS = 36500


class ChainState(models.TextChoices):
    """Where an on-chain action stands: the portal's row moves on the chain's confirmation."""

    PENDING = "pending", "pending"
    CONFIRMED = "confirmed", "confirmed"
    FAILED = "failed", "failed"


class Approval(models.TextChoices):
    """Whether an operator let a sign-up onto the chain (SIGNUP_APPROVAL); approved by default."""

    APPROVED = "approved", "approved"
    AWAITING = "awaiting", "awaiting an operator's approval"
    REFUSED = "refused", "refused by an operator"


class Owner(models.Model):
    """A robot owner: a Django user with a custodial EOA registered on chain."""

    user = models.OneToOneField(
        settings.AUTH_USER_MODEL, on_delete=models.PROTECT, related_name="owner"
    )
    eoa_address = models.CharField(max_length=42, unique=True)
    # eth-account private key, wrapped under the KEK (accounts.keywrap).
    eoa_key_wrapped = models.BinaryField()
    chain_state = models.CharField(
        max_length=16, choices=ChainState.choices, default=ChainState.PENDING
    )
    fund_tx = models.CharField(max_length=66, blank=True)
    enroll_tx = models.CharField(max_length=66, blank=True)
    register_tx = models.CharField(max_length=66, blank=True)
    registered_block = models.BigIntegerField(null=True, blank=True)
    chain_error = models.CharField(max_length=300, blank=True)
    approval = models.CharField(max_length=16, choices=Approval.choices, default=Approval.APPROVED)
    approved_by = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
        help_text="the operator who approved or refused the sign-up",
    )
    approved_at = models.DateTimeField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    # The owner deleted the account: no sign-in, credentials revoked, records deleted; the
    # row (and its user, so the username) stays, so that nobody can take the name over.
    deleted_at = models.DateTimeField(null=True, blank=True)
    # What the username looks like (accounts.usernames.username_skeleton): unique among owners,
    # so that no new name is confusable with a taken one. `name_lookalike` marks the owners
    # registered before the rule beside an older look-alike: they keep their name, and
    # neither name resolves a grant (sharing.selectors.grants.owner_resolve).
    name_skeleton = models.CharField(max_length=750, db_index=True)
    name_lookalike = models.BooleanField(default=False)

    class Meta:
        ordering = ["user__username"]
        constraints = [
            models.UniqueConstraint(
                fields=["name_skeleton"],
                condition=models.Q(name_lookalike=False),
                name="owner_name_skeleton_unique",
            )
        ]

    def __str__(self) -> str:
        return self.user.username

    def save(self, *args, **kwargs) -> None:
        if not self.name_skeleton:  # an owner made without owner_create (a script's, a test's)
            self.name_skeleton = username_skeleton(self.user.username)
        super().save(*args, **kwargs)

    @property
    def username(self) -> str:
        return self.user.username


class OwnerKey(models.Model):
    """One SM4 key of an owner; the current one seals new data, older ones stay readable."""

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="keys")
    key_id = models.CharField(max_length=16, help_text="hex of the first 8 bytes of SM3(key)")
    # The SM4 key itself, wrapped under the KEK; never stored in plaintext.
    key_wrapped = models.BinaryField()
    commitment = models.CharField(max_length=66)
    is_current = models.BooleanField(default=True)
    chain_state = models.CharField(
        max_length=16, choices=ChainState.choices, default=ChainState.PENDING
    )
    tx_hash = models.CharField(max_length=66, blank=True)
    block_number = models.BigIntegerField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    retired_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at"]
        constraints = [
            models.UniqueConstraint(fields=["owner", "key_id"], name="one_key_id_per_owner"),
            models.UniqueConstraint(
                fields=["owner"],
                condition=models.Q(is_current=True),
                name="one_current_key_per_owner",
            ),
        ]

    def __str__(self) -> str:
        return f"{self.owner} key {self.key_id}"


class Robot(models.Model):
    """A robot of one owner; it authenticates with a token whose hash alone is stored."""

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="robots")
    name = models.CharField(max_length=100)
    token_hash = models.CharField(max_length=64, unique=True)
    token_prefix = models.CharField(
        max_length=8, help_text="first characters, to tell tokens apart"
    )
    last_seq = models.BigIntegerField(default=-1)
    # When its last upload was stored: what the silent-robot alert watches.
    last_upload_at = models.DateTimeField(null=True, blank=True)
    # What the robot's agent subscribes to: [{"name": "/robot/odom", "type": "nav_msgs/..."}].
    topics = models.JSONField(default=default_robot_topics, validators=[validate_robot_topics])
    is_active = models.BooleanField(default=True)
    # Days of its records kept (by capture time); None: kept until deleted by hand.
    retention_days = models.PositiveIntegerField(null=True, blank=True)
    # The robot's SM2 public key (`04||x||y` hex) when it was paired (RobotPairing): the
    # owner's SM4 key is sent to it encrypted to this key. Empty for robots added by hand.
    public_key = models.CharField(max_length=130, blank=True)
    paired_at = models.DateTimeField(null=True, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    revoked_at = models.DateTimeField(null=True, blank=True)
    # A paired robot signs every envelope with its SM2 key (DESIGN.md "Provenance"): the key's
    # hash (SM3 of x||y, hex), registered on chain by the owner's EOA (robotKeyAdd) when the
    # pairing is approved, and revoked there (robotKeyRevoke) when the robot is unpaired. Blank
    # for robots added by hand: their records are unsigned.
    key_hash = models.CharField(max_length=64, blank=True, db_index=True)
    key_chain_state = models.CharField(max_length=16, choices=ChainState.choices, blank=True)
    key_added_block = models.BigIntegerField(null=True, blank=True)
    key_revoke_state = models.CharField(max_length=16, choices=ChainState.choices, blank=True)

    class Meta:
        ordering = ["owner", "name"]
        constraints = [
            models.UniqueConstraint(fields=["owner", "name"], name="robot_name_unique_per_owner"),
        ]

    def __str__(self) -> str:
        return f"{self.owner}/{self.name}"


class RobotPairing(models.Model):
    """A robot asking to be paired: it sent its SM2 public key and holds a secret whose hash
    alone is kept. An owner who types the short code the robot printed approves or refuses
    it; on approval a Robot is made, its token kept here encrypted to the robot's SM2 key
    until the robot collects it, once, with its secret."""

    class State(models.TextChoices):
        PENDING = "pending", "waiting for an owner"
        APPROVED = "approved", "approved, not collected yet"
        DELIVERED = "delivered", "approved and collected by the robot"
        REFUSED = "refused", "refused"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    code = models.CharField(max_length=16, unique=True, help_text="what the robot printed")
    secret_hash = models.CharField(max_length=64, help_text="SHA-256 of the robot's secret")
    name = models.CharField(max_length=100)
    public_key = models.CharField(max_length=130, help_text="SM2, `04||x||y` hex")
    state = models.CharField(max_length=16, choices=State.choices, default=State.PENDING)
    owner = models.ForeignKey(
        Owner, on_delete=models.CASCADE, null=True, blank=True, related_name="pairings"
    )
    robot = models.OneToOneField(
        Robot, on_delete=models.SET_NULL, null=True, blank=True, related_name="pairing"
    )
    # The robot's token, SM2-encrypted to `public_key` (C1C3C2 hex), until it is collected.
    token_sm2 = models.TextField(blank=True)
    answered_by = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
    )
    created_at = models.DateTimeField(auto_now_add=True)
    expires_at = models.DateTimeField()
    answered_at = models.DateTimeField(null=True, blank=True)
    delivered_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["state", "expires_at"], name="robot_pairing_state")]

    def __str__(self) -> str:
        return f"pairing {self.code} ({self.name}, {self.state})"

    @property
    def is_expired(self) -> bool:
        return self.expires_at <= timezone.now()


class OwnerToken(models.Model):
    """An owner's API credential for scripts: scoped, expiring, revocable; only its hash kept.

    Robot tokens upload; an owner token reads content (`read`) and grants or revokes
    (`share`) on the owner's behalf, as a browser session does.
    """

    class Scope(models.TextChoices):
        READ = "read", "read records and their content"
        SHARE = "share", "grant and revoke access"
        DELETE = "delete", "delete records"

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="api_tokens")
    name = models.CharField(max_length=100)
    token_hash = models.CharField(max_length=64, unique=True)
    token_prefix = models.CharField(
        max_length=12, help_text="first characters, to tell tokens apart"
    )
    scopes = models.JSONField(default=list, help_text='a subset of ["read", "share", "delete"]')
    expires_at = models.DateTimeField()
    created_at = models.DateTimeField(auto_now_add=True)
    last_used_at = models.DateTimeField(null=True, blank=True)
    revoked_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at"]

    def __str__(self) -> str:
        return f"{self.owner}/{self.name} ({self.token_prefix}…)"

    @property
    def is_live(self) -> bool:
        return self.revoked_at is None and self.expires_at > timezone.now()


class AccountEvent(models.Model):
    """Something that happened to an owner's account that the owner sees on the security page:
    an operator's change, a credential made or revoked, an identity check that failed.

    Record-level alarms (tampering, forged uploads) are sharing.models.SecurityEvent.
    """

    class Kind(models.TextChoices):
        ADMIN_ACTION = "admin_action", "an operator changed the account"
        IDENTITY_MISMATCH = "identity_mismatch", "the key commitment on chain differs"
        TOKEN_CREATED = "token_created", "API token created"
        TOKEN_REVOKED = "token_revoked", "API token revoked"
        ROBOT_TOKEN_REVOKED = "robot_token_revoked", "robot token revoked"
        ROBOT_PAIRED = "robot_paired", "robot paired"
        ROBOT_PAIRING_REFUSED = "robot_pairing_refused", "robot pairing refused"
        ROBOT_KEY_TAKEN = (
            "robot_key_taken",
            "robot pairing refused: its key is another owner's robot's",
        )
        PAIRING_SECRET_MISMATCH = (
            "pairing_secret_mismatch",
            "someone without the robot's secret asked for its pairing answer",
        )
        SIGNUP_APPROVED = "signup_approved", "sign-up approved"
        SIGNUP_REFUSED = "signup_refused", "sign-up refused"
        RECORDS_DELETED = "records_deleted", "records deleted"
        RETENTION_SET = "retention_set", "robot's retention changed"
        ACCOUNT_DELETED = "account_deleted", "account deleted"

    # Kinds the owner is alerted to (an alarm on the security page, a notice on sign-in).
    ALARM_KINDS = (Kind.IDENTITY_MISMATCH, Kind.PAIRING_SECRET_MISMATCH)

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="account_events")
    kind = models.CharField(max_length=32, choices=Kind.choices)
    actor = models.ForeignKey(
        settings.AUTH_USER_MODEL,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="+",
        help_text="who did it: the owner, an operator, or empty for the portal itself",
    )
    detail = models.JSONField(default=dict)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at", "-id"]
        indexes = [models.Index(fields=["owner", "-created_at"], name="account_event_owner")]

    def __str__(self) -> str:
        return f"{self.owner}: {self.kind} at {self.created_at:%Y-%m-%d %H:%M:%S}"


class ChainActivity(models.Model):
    """One of an owner's transactions as the worker saw its receipt: the audit page's index,
    so that pages never scan the chain's logs."""

    class Kind(models.TextChoices):
        FUNDED = "funded", "EOA funded"
        ENROLLED = "enrolled", "enrolled"
        REGISTERED = "registered", "key commitment registered"
        KEY_ROTATED = "key_rotated", "key rotated"
        ANCHORED = "anchored", "records anchored"
        GRANTED = "granted", "access granted"
        REVOKED = "revoked", "access revoked"
        ROBOT_KEY_ADDED = "robot_key_added", "robot key registered"
        ROBOT_KEY_REVOKED = "robot_key_revoked", "robot key revoked"

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="chain_activity")
    # The other side of a grant or revocation (who sees it as "received").
    counterpart = models.ForeignKey(
        Owner, on_delete=models.SET_NULL, null=True, blank=True, related_name="+"
    )
    kind = models.CharField(max_length=24, choices=Kind.choices)
    tx_hash = models.CharField(max_length=66)
    block_number = models.BigIntegerField(null=True, blank=True)
    record_count = models.PositiveIntegerField(default=0)
    detail = models.JSONField(default=dict)
    at = models.DateTimeField(default=timezone.now, help_text="when the receipt was seen")

    class Meta:
        ordering = ["-at", "-id"]
        constraints = [
            models.UniqueConstraint(
                fields=["owner", "kind", "tx_hash"], name="one_activity_per_owner_kind_tx"
            ),
        ]
        indexes = [
            models.Index(fields=["owner", "-at"], name="chain_activity_owner"),
            models.Index(fields=["counterpart", "-at"], name="chain_activity_counterpart"),
        ]

    def __str__(self) -> str:
        return f"{self.owner}: {self.kind} {self.tx_hash}"


class EoaFunding(models.Model):
    """Ether the operator sent to an owner's EOA: the ledger the funding budget is kept on."""

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="fundings")
    amount_wei = models.DecimalField(max_digits=78, decimal_places=0)
    tx_hash = models.CharField(max_length=66, blank=True)
    reason = models.CharField(max_length=32, default="registration")
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["created_at"], name="eoa_funding_created")]

    def __str__(self) -> str:
        return f"{self.amount_wei} wei to {self.owner} ({self.reason})"


class SecretFingerprint(models.Model):
    """A fingerprint of a secret kept outside the database (the KEK), so that a portal started
    with another secret than the one its rows were wrapped under refuses to serve."""

    name = models.CharField(max_length=32, primary_key=True)
    fingerprint = models.CharField(max_length=64)
    created_at = models.DateTimeField(auto_now_add=True)

    def __str__(self) -> str:
        return f"{self.name}: {self.fingerprint[:16]}…"
