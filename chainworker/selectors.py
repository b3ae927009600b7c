"""Reads about the chain and the portal's record of it."""

from chainworker.models import Deployment, OperatorAlert


def deployment_active(*, chain_id: int, genesis_hash: str) -> Deployment | None:
    return Deployment.objects.filter(
        chain_id=chain_id, genesis_hash=genesis_hash, is_active=True
    ).first()


def operator_alert_open(*, kind: str, subject: str) -> OperatorAlert | None:
    """The open operator alert of this kind and subject, if one is."""
    return OperatorAlert.objects.filter(kind=kind, subject=subject, resolved_at=None).first()


def operator_alerts_open_count() -> int:
    """How many operator alerts are open (for /metrics: portal/scrape.py)."""
    return OperatorAlert.objects.filter(resolved_at=None).count()
