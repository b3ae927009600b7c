"""A grant's scope: which of the owner's records it covers, and its SM3 commitment on chain.

A scope is a RecordSelection (sharing/selection.py); here is what a grant adds to it (both ends
of its window from 1970 on, its own words for the limits) and its bytes. Pure functions (no
database): the portal enforces a scope in its queries and at every view, and the chain holds
`scope_commitment(scope)` with the grant (authorityGrantScoped), so that the check at view can
compare the two. docs/grants.md defines the bytes:

    "AuthROS/grant-scope/v1"                      22 bytes, ASCII
    robot count R                                 2 bytes
    R robot ids                                   16 bytes each (UUID bytes), ascending
    topic count T                                 2 bytes
    T topics, ascending by their UTF-8 bytes      each: length L (2 bytes), L bytes UTF-8
    window flags                                  1 byte: bit 0 `since` given, bit 1 `until`
    since                                         8 bytes, microseconds since 1970 (0 if not)
    until                                         8 bytes, microseconds since 1970 (0 if not)

All integers big-endian. An empty list means "all" (robots or topics); the capture-time window
is half-open, [since, until). The commitment is SM3 of these bytes, except for the scope of all
records (no robots, no topics, no window), whose commitment is 32 zero bytes: what
`authorityGrant` leaves on chain, so grants made before scopes existed keep their meaning.
"""

import struct
import uuid
from collections.abc import Iterable
from datetime import UTC, datetime

from sharing.selection import (
    MAX_SELECTED_ROBOTS,
    MAX_SELECTED_TOPICS,
    TOO_MANY_ROBOTS,
    TOO_MANY_TOPICS,
    RecordSelection,
    SelectionError,
)
from smcrypto import sm3

SCOPE_DOMAIN = b"AuthROS/grant-scope/v1"
ALL_RECORDS_COMMITMENT = b"\x00" * 32
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
MAX_UINT64 = 2**64 - 1
# A grant's own words for the selection's limits; its other refusals say what the selection's do.
_GRANT_LIMITS = {
    TOO_MANY_ROBOTS: f"a grant can name at most {MAX_SELECTED_ROBOTS} robots",
    TOO_MANY_TOPICS: f"a grant can name at most {MAX_SELECTED_TOPICS} topics",
}


class ScopeError(ValueError):
    """A scope that cannot be granted; the message says why, in words for the owner."""


def scope_make(
    *,
    robots: Iterable[uuid.UUID | str] = (),
    topics: Iterable[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
) -> RecordSelection:
    """The canonical scope of these values (RecordSelection.of, whose checks hold), with both
    ends of its window from 1970 on, as its encoding holds them; ScopeError otherwise."""
    try:
        scope = RecordSelection.of(robots=robots, topics=topics, since=since, until=until)
    except SelectionError as exc:
        raise ScopeError(_GRANT_LIMITS.get(exc.rule, str(exc))) from None
    for which, moment in (("start", scope.since), ("end", scope.until)):
        if moment is not None and not 0 <= _micros(moment) <= MAX_UINT64:
            raise ScopeError(f"the {which} of the time window must be after 1970-01-01")
    return scope


def scope_encode(scope: RecordSelection) -> bytes:
    """The canonical bytes of a scope (module docstring)."""
    parts = [SCOPE_DOMAIN, struct.pack(">H", len(scope.robots))]
    parts += [robot.bytes for robot in sorted(scope.robots, key=lambda r: r.bytes)]
    topics = sorted(topic.encode("utf-8") for topic in scope.topics)
    parts.append(struct.pack(">H", len(topics)))
    parts += [struct.pack(">H", len(topic)) + topic for topic in topics]
    flags = (scope.since is not None) | (scope.until is not None) << 1
    parts.append(struct.pack(">BQQ", flags, _micros(scope.since) or 0, _micros(scope.until) or 0))
    return b"".join(parts)


def scope_commitment(scope: RecordSelection) -> bytes:
    """What the chain holds for the scope: SM3 of its bytes; zeros for all records."""
    if scope.is_all:
        return ALL_RECORDS_COMMITMENT
    return sm3.sm3_digest(scope_encode(scope))


def expiry_seconds(expires_at: datetime | None) -> int:
    """A grant's expiry as the chain holds it: unix seconds, 0 for never."""
    if expires_at is None:
        return 0
    return int(expires_at.timestamp())


def _micros(moment: datetime | None) -> int | None:
    if moment is None:
        return None
    delta = moment - EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds
