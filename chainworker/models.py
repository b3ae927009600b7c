"""What the portal knows about the chain: where the AuthROS contract lives."""

from django.db import models


class Deployment(models.Model):
    """One deployment of the AuthROS contract; at most one is active per chain."""

    chain_id = models.BigIntegerField()
    genesis_hash = models.CharField(max_length=66)
    address = models.CharField(max_length=42)
    tx_hash = models.CharField(max_length=66)
    block_number = models.BigIntegerField()
    deployer = models.CharField(max_length=42)
    compiler_version = models.CharField(max_length=100)
    source_keccak = models.CharField(max_length=66)
    rpc_url = models.CharField(max_length=200, blank=True)
    is_active = models.BooleanField(default=True)
    created_at = models.DateTimeField(auto_now_add=True)

    class Meta:
        ordering = ["-created_at"]
        constraints = [
            models.UniqueConstraint(
                fields=["chain_id", "genesis_hash"],
                condition=models.Q(is_active=True),
                name="one_active_deployment_per_chain",
            ),
        ]

    def __str__(self) -> str:
        state = "active" if self.is_active else "retired"
        return f"AuthROS at {self.address} on chain {self.chain_id} ({state})"


class OperatorAlert(models.Model):
    """Something only the operator can fix (the funding budget is spent, the operator cannot
    pay); at most one open alert per kind and subject, resolved when the cause is gone."""

    class Kind(models.TextChoices):
        FUNDING_BUDGET_SPENT = "funding-budget-spent", "EOA funding budget spent"
        OPERATOR_CANNOT_PAY = "operator-cannot-pay", "Operator cannot pay"
        OPERATOR_LOW_BALANCE = "operator-low-balance", "Operator balance low"

    # Free text, not choices: other chain work adds kinds without a migration.
    kind = models.CharField(max_length=40)
    subject = models.CharField(max_length=100)
    detail = models.JSONField(default=dict, blank=True)
    created_at = models.DateTimeField(auto_now_add=True)
    last_seen_at = models.DateTimeField(auto_now=True)
    resolved_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at"]
        constraints = [
            models.UniqueConstraint(
                fields=["kind", "subject"],
                condition=models.Q(resolved_at__isnull=True),
                name="one_open_operator_alert",
            ),
        ]

    def __str__(self) -> str:
        state = "resolved" if self.resolved_at else "open"
        return f"{self.kind} on {self.subject} ({state})"
