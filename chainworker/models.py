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
