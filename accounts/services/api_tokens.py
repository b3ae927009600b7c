"""Owners' API tokens: their scripts read and share with scopes, never with a robot's token.

A token's key is shown once and only its hash kept; it expires within a year, its last use
is noted at most once a minute, and its creation and revocation are shown to the owner.
"""

import secrets
from collections.abc import Sequence
from datetime import timedelta

from django.contrib.auth.base_user import AbstractBaseUser
from django.db import transaction
from django.utils import timezone

from accounts.errors import InvalidOwnerToken
from accounts.events import account_event_record
from accounts.models import AccountEvent, Owner, OwnerToken
from accounts.selectors import OWNER_TOKEN_PREFIX, robot_token_hash

OWNER_TOKEN_BYTES = 32
OWNER_TOKEN_MAX_LIFETIME = timedelta(days=365)
# A token's last use is written at most this often, so that most requests write nothing.
OWNER_TOKEN_USE_RESOLUTION = timedelta(minutes=1)


def owner_token_create(
    *, owner: Owner, name: str, scopes: Sequence[str], expires_in: timedelta
) -> tuple[OwnerToken, str]:
    """An API token for the owner's scripts; the key is returned once and only its hash kept.

    `scopes` is a non-empty subset of OwnerToken.Scope; the token expires after `expires_in`,
    at most OWNER_TOKEN_MAX_LIFETIME. The owner's security page shows it was made.
    """
    name = name.strip() if isinstance(name, str) else ""
    if not name or len(name) > 100 or "\x00" in name:
        raise InvalidOwnerToken("a token name has 1 to 100 characters")
    allowed = OwnerToken.Scope.values
    if isinstance(scopes, str) or not scopes or not set(scopes) <= set(allowed):
        raise InvalidOwnerToken(f"scopes are one or more of: {', '.join(allowed)}")
    if not isinstance(expires_in, timedelta) or not (
        timedelta(0) < expires_in <= OWNER_TOKEN_MAX_LIFETIME
    ):
        raise InvalidOwnerToken(
            f"a token expires within {OWNER_TOKEN_MAX_LIFETIME.days} days of being made"
        )
    key = OWNER_TOKEN_PREFIX + secrets.token_urlsafe(OWNER_TOKEN_BYTES)
    with transaction.atomic():
        token = OwnerToken.objects.create(
            owner=owner,
            name=name,
            token_hash=robot_token_hash(key),
            token_prefix=key[:12],
            scopes=[scope for scope in allowed if scope in scopes],
            expires_at=timezone.now() + expires_in,
        )
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.TOKEN_CREATED,
            actor=owner.user,
            detail=_owner_token_detail(token),
        )
    return token, key


def owner_token_revoke(*, token: OwnerToken, actor: AbstractBaseUser | None) -> OwnerToken:
    """The token stops working at once (401); what it granted is
    sharing.services.grants.grants_undo_made_with's to take back or restore."""
    with transaction.atomic():
        revoked = OwnerToken.objects.filter(pk=token.pk, revoked_at__isnull=True).update(
            revoked_at=timezone.now()
        )
        if revoked:
            account_event_record(
                owner=token.owner,
                kind=AccountEvent.Kind.TOKEN_REVOKED,
                actor=actor,
                detail=_owner_token_detail(token),
            )
    token.refresh_from_db()
    return token


def owner_token_mark_used(*, token: OwnerToken) -> None:
    """Note that the token was just used, at most once per OWNER_TOKEN_USE_RESOLUTION."""
    now = timezone.now()
    last = token.last_used_at
    if last is not None and now - last < OWNER_TOKEN_USE_RESOLUTION:
        return
    OwnerToken.objects.filter(pk=token.pk).exclude(
        last_used_at__gt=now - OWNER_TOKEN_USE_RESOLUTION
    ).update(last_used_at=now)
    token.last_used_at = now


def _owner_token_detail(token: OwnerToken) -> dict[str, object]:
    """What the security page says about a token: never its key."""
    return {
        "token": token.name,
        "token_id": token.pk,
        "prefix": token.token_prefix,
        "scopes": list(token.scopes),
        "expires_at": token.expires_at.isoformat(),
    }
