"""Reads about the chain and the portal's record of it."""

from chainworker.models import Deployment


def deployment_active(*, chain_id: int, genesis_hash: str) -> Deployment | None:
    return Deployment.objects.filter(
        chain_id=chain_id, genesis_hash=genesis_hash, is_active=True
    ).first()
