"""The owner's security page's entries: what happened to an account (an operator's action, a
credential made or revoked, a failed identity check), written by the services that did it."""

from django.contrib.auth.base_user import AbstractBaseUser

from accounts.models import AccountEvent, Owner


def account_event_record(
    *,
    owner: Owner,
    kind: str,
    actor: AbstractBaseUser | None = None,
    detail: dict[str, object] | None = None,
) -> AccountEvent:
    """One entry on the owner's security page. `actor` is who did it (the owner, an operator,
    or None for the portal itself); `detail` is shown to the owner: never put a secret in it."""
    if kind not in AccountEvent.Kind.values:
        raise ValueError(f"unknown account event kind {kind!r}")
    return AccountEvent.objects.create(owner=owner, kind=kind, actor=actor, detail=detail or {})
