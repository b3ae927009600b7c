"""The audit page's index of owners' transactions: one row per transaction whose receipt the
worker saw (funding, registration, key rotations here; anchoring and grants in sharing)."""

from accounts.models import ChainActivity, Owner


def chain_activity_record(
    *,
    owner: Owner,
    kind: str,
    tx_hash: str,
    block_number: int | None = None,
    counterpart: Owner | None = None,
    record_count: int = 0,
    detail: dict[str, object] | None = None,
) -> ChainActivity | None:
    """Index a transaction of the owner's whose receipt the worker saw, for the audit page.

    Idempotent: a retry that sees the same transaction again updates its row (one per
    owner, kind and transaction) and keeps the time it was first seen. Nothing is written
    for an empty `tx_hash` (nothing was sent).
    """
    if not tx_hash:
        return None
    if kind not in ChainActivity.Kind.values:
        raise ValueError(f"unknown chain activity kind {kind!r}")
    activity, _created = ChainActivity.objects.update_or_create(
        owner=owner,
        kind=kind,
        tx_hash=tx_hash,
        defaults={
            "block_number": block_number,
            "counterpart": counterpart,
            "record_count": record_count,
            "detail": detail or {},
        },
    )
    return activity
