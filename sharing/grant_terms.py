"""What a grant covers and until when: GrantTerms, the checked way to make them, and
whether the chain's grant matches the portal's.

Used by the grant services (sharing/services/grants.py, grant_chain.py) and by the readers of
grants (the check at view, the API and the pages), so it sits beside them rather than in
either. The scope's bytes and commitment are sharing/scope.py's.
"""

import dataclasses
import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from django.utils import timezone

from accounts.models import Owner, Robot
from chainworker.codec import OnChainGrant
from sharing.errors import InvalidGrantTerms
from sharing.models import Grant
from sharing.scope import ScopeError, expiry_seconds, scope_commitment, scope_make
from sharing.selection import RecordSelection, iso_utc


@dataclass(frozen=True)
class GrantTerms:
    """What a grant covers and until when: its scope (all records by default) and expiry."""

    scope: RecordSelection = dataclasses.field(default_factory=RecordSelection)
    expires_at: datetime | None = None

    @classmethod
    def of(cls, grant: Grant) -> "GrantTerms":
        return cls(scope=grant.scope, expires_at=grant.expires_at)

    def within(self, other: "GrantTerms") -> bool:
        """Whether these terms give no more than `other`: a scope inside its scope, and an
        expiry no later (never expiring is the latest)."""
        if other.expires_at is not None and (
            self.expires_at is None or self.expires_at > other.expires_at
        ):
            return False
        return self.scope.within(other.scope)

    def as_json(self) -> dict[str, object]:
        """The terms as a GrantChange keeps them: the scope's JSON and the expiry."""
        return {**self.scope.as_json(), "expires_at": iso_utc(self.expires_at)}

    @classmethod
    def from_json(cls, value: dict) -> "GrantTerms":
        expiry = value.get("expires_at")
        return cls(
            scope=RecordSelection.from_json(value),
            expires_at=datetime.fromisoformat(expiry) if expiry else None,
        )


ALL_RECORDS_FOREVER = GrantTerms()
# An expiry this close to now could pass before the grant is confirmed on chain.
MIN_GRANT_LIFETIME = timedelta(minutes=5)


def grant_terms_make(
    *,
    owner: Owner,
    robots: Sequence[uuid.UUID | str] = (),
    topics: Sequence[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
    expires_at: datetime | None = None,
) -> GrantTerms:
    """The terms of a grant of `owner`'s, checked: robots must be the owner's, the window
    ordered, the expiry at least MIN_GRANT_LIFETIME ahead. InvalidGrantTerms says what is
    wrong, in words for the owner."""
    try:
        scope = scope_make(robots=robots, topics=topics, since=since, until=until)
    except ScopeError as exc:
        raise InvalidGrantTerms(_sentence(str(exc))) from None
    if scope.robots:
        own = set(
            Robot.objects.filter(owner=owner, pk__in=scope.robots).values_list("pk", flat=True)
        )
        if len(own) != len(scope.robots):
            raise InvalidGrantTerms("A grant can only name your own robots.")
    if expires_at is not None:
        if expires_at.tzinfo is None:
            raise InvalidGrantTerms("The expiry needs a time zone.")
        expires_at = expires_at.astimezone(UTC).replace(microsecond=0)  # whole seconds on chain
        if expires_at < timezone.now() + MIN_GRANT_LIFETIME:
            raise InvalidGrantTerms(
                "The expiry must be at least "
                f"{int(MIN_GRANT_LIFETIME.total_seconds() // 60)} minutes in the future."
            )
        if expiry_seconds(expires_at) >= 2**64:
            raise InvalidGrantTerms("The expiry is too far in the future.")
    return GrantTerms(scope=scope, expires_at=expires_at)


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


def grant_on_chain_matches(grant: Grant, on_chain: OnChainGrant) -> bool:
    """Whether the chain's grant (grantOf) is the portal's `grant`: live at the latest block,
    with the same scope commitment and expiry."""
    return (
        on_chain.live
        and on_chain.scope == scope_commitment(grant.scope)
        and on_chain.expiry == grant.expiry
    )
