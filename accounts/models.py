"""Owners, their SM4 keys and custodial EOAs, and their robots."""

import uuid

from django.conf import settings
from django.core.exceptions import ValidationError
from django.db import models

from accounts.agent_config import DEFAULT_TOPICS, InvalidTopics, topics_as_list, topics_parse


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


class ChainState(models.TextChoices):
    """Where an on-chain action stands: the portal's row moves on the chain's confirmation."""

    PENDING = "pending", "pending"
    CONFIRMED = "confirmed", "confirmed"
    FAILED = "failed", "failed"


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
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["user__username"]

    def __str__(self) -> str:
        return self.user.username

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
    # What the robot's agent subscribes to: [{"name": "/robot/odom", "type": "nav_msgs/..."}].
    topics = models.JSONField(default=default_robot_topics, validators=[validate_robot_topics])
    is_active = models.BooleanField(default=True)
    created_at = models.DateTimeField(auto_now_add=True)
    revoked_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["owner", "name"]
        constraints = [
            models.UniqueConstraint(fields=["owner", "name"], name="robot_name_unique_per_owner"),
        ]

    def __str__(self) -> str:
        return f"{self.owner}/{self.name}"
