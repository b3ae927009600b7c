"""What owners are told, and how: their choices, their webhook endpoints, each alert and each
attempt to deliver it, and the conditions (a silent robot, low gas) that alert once per episode.
"""

import uuid

from django.db import models

from accounts.models import Owner


class AlertKind(models.TextChoices):
    RECORD_TAMPERED = "record_tampered", "A record was found tampered"
    ANCHORING_FAILED = "anchoring_failed", "Anchoring failed"
    GRANT_RECEIVED = "grant_received", "Someone granted you access"
    GRANT_REVOKED = "grant_revoked", "Someone revoked your access"
    ROBOT_SILENT = "robot_silent", "A robot went silent"
    GAS_LOW = "gas_low", "Your account is low on gas"
    RECORDS_MISSING = "records_missing", "Records of a robot are missing"
    ROBOT_KEY_DISPUTED = "robot_key_disputed", "A robot's key is claimed by another owner"
    TEST = "test", "A test alert"


class AlertPreferences(models.Model):
    """One owner's choices: which alerts go by e-mail, which to the webhooks, and the limits of
    the two watched conditions (empty: not watched)."""

    owner = models.OneToOneField(Owner, on_delete=models.CASCADE, related_name="alert_preferences")
    email = models.EmailField(blank=True, help_text="where e-mail alerts go")
    # Set when the owner opened the link sent to `email`; alerts go by e-mail only then.
    email_verified_at = models.DateTimeField(null=True, blank=True)
    email_kinds = models.JSONField(default=list, blank=True)
    webhook_kinds = models.JSONField(default=list, blank=True)
    robot_silent_minutes = models.PositiveIntegerField(null=True, blank=True)
    gas_low_below_wei = models.DecimalField(max_digits=78, decimal_places=0, null=True, blank=True)
    updated_at = models.DateTimeField(auto_now=True)

    def __str__(self) -> str:
        return f"alert preferences of {self.owner}"


class WebhookEndpoint(models.Model):
    """A URL an owner's alerts are POSTed to, signed with a secret shown once (kept wrapped
    under the master key: the portal must sign with it)."""

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="webhook_endpoints")
    url = models.URLField(max_length=500)
    secret_wrapped = models.BinaryField()
    secret_prefix = models.CharField(max_length=12, help_text="first characters of the secret")
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["created_at"]

    def __str__(self) -> str:
        return f"{self.owner}: {self.url}"


class Alert(models.Model):
    """One thing an owner is told about."""

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="alerts")
    kind = models.CharField(max_length=32, choices=AlertKind.choices)
    subject = models.CharField(max_length=100, help_text="what it is about: a record, a robot")
    summary = models.CharField(max_length=300)
    detail = models.JSONField(default=dict)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["owner", "-created_at"], name="alert_owner_created")]

    def __str__(self) -> str:
        return f"{self.owner}: {self.kind} {self.subject}"


class AlertDelivery(models.Model):
    """One alert to one channel (an e-mail address or a webhook endpoint), with its attempts:
    the delivery log the owner sees."""

    class Channel(models.TextChoices):
        EMAIL = "email", "e-mail"
        WEBHOOK = "webhook", "webhook"

    class Status(models.TextChoices):
        PENDING = "pending", "pending"
        SENT = "sent", "sent"
        FAILED = "failed", "failed"

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    alert = models.ForeignKey(Alert, on_delete=models.CASCADE, related_name="deliveries")
    channel = models.CharField(max_length=16, choices=Channel.choices)
    endpoint = models.ForeignKey(
        WebhookEndpoint,
        on_delete=models.SET_NULL,
        null=True,
        blank=True,
        related_name="deliveries",
    )
    target = models.CharField(max_length=500, help_text="the address or URL when it was made")
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.PENDING)
    attempts = models.PositiveIntegerField(default=0)
    response_status = models.PositiveIntegerField(null=True, blank=True)
    last_error = models.CharField(max_length=300, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    updated_at = models.DateTimeField(auto_now=True)
    sent_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["status", "updated_at"], name="alert_delivery_status")]

    def __str__(self) -> str:
        return f"{self.alert} by {self.channel} ({self.status})"


class AlertCondition(models.Model):
    """An ongoing state an owner was alerted to (a robot silent, gas low, a record tampered):
    while it is open no new alert of it is made; it closes when the state ends."""

    owner = models.ForeignKey(Owner, on_delete=models.CASCADE, related_name="alert_conditions")
    kind = models.CharField(max_length=32, choices=AlertKind.choices)
    subject = models.CharField(max_length=100)
    started_at = models.DateTimeField(auto_now_add=True)
    resolved_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-started_at"]
        constraints = [
            models.UniqueConstraint(
                fields=["owner", "kind", "subject"],
                condition=models.Q(resolved_at__isnull=True),
                name="one_open_alert_condition",
            ),
        ]

    def __str__(self) -> str:
        state = "resolved" if self.resolved_at else "open"
        return f"{self.owner}: {self.kind} {self.subject} ({state})"
