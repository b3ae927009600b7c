"""A grant's scope: which of the owner's records it covers, and its SM3 commitment on chain.

Pure values and functions (no database): the portal enforces a scope in its queries and at
every view, and the chain holds `scope_commitment(scope)` with the grant (authorityGrantScoped),
so that the check at view can compare the two. docs/grants.md defines the bytes:

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
from dataclasses import dataclass
from datetime import UTC, datetime

from smcrypto import sm3

SCOPE_DOMAIN = b"AuthROS/grant-scope/v1"
ALL_RECORDS_COMMITMENT = b"\x00" * 32
EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
# Bounds of a scope, so that its encoding and the queries it makes stay small.
MAX_SCOPE_ROBOTS = 100
MAX_SCOPE_TOPICS = 100
MAX_TOPIC_LENGTH = 255
MAX_UINT64 = 2**64 - 1


class ScopeError(ValueError):
    """A scope that cannot be granted; the message says why, in words for the owner."""


@dataclass(frozen=True)
class GrantScope:
    """Robots (ids) and topics a grant covers (empty: all) and its capture-time window."""

    robots: tuple[uuid.UUID, ...] = ()
    topics: tuple[str, ...] = ()
    since: datetime | None = None
    until: datetime | None = None

    @property
    def is_all(self) -> bool:
        return not (self.robots or self.topics or self.since or self.until)

    def covers(self, *, robot_id: uuid.UUID | str, topic: str, captured_at: datetime) -> bool:
        """Whether a record of this robot and topic, captured then, is inside the scope."""
        if self.robots and uuid.UUID(str(robot_id)) not in self.robots:
            return False
        if self.topics and topic not in self.topics:
            return False
        if self.since is not None and captured_at < self.since:
            return False
        return self.until is None or captured_at < self.until


def scope_make(
    *,
    robots: Iterable[uuid.UUID | str] = (),
    topics: Iterable[str] = (),
    since: datetime | None = None,
    until: datetime | None = None,
) -> GrantScope:
    """The canonical scope of these values (deduplicated, sorted, times in UTC to the
    microsecond); ScopeError for values no grant may have."""
    try:
        robot_ids = sorted({uuid.UUID(str(robot)) for robot in robots}, key=lambda r: r.bytes)
    except ValueError:
        raise ScopeError("a robot is named by its id (a UUID)") from None
    if len(robot_ids) > MAX_SCOPE_ROBOTS:
        raise ScopeError(f"a grant can name at most {MAX_SCOPE_ROBOTS} robots")
    topic_set = set()
    for topic in topics:
        if not isinstance(topic, str) or not topic.strip():
            raise ScopeError("a topic cannot be empty")
        if len(topic) > MAX_TOPIC_LENGTH or "\x00" in topic or not _is_utf8(topic):
            raise ScopeError(
                f"a topic is at most {MAX_TOPIC_LENGTH} characters of text, without NUL characters"
            )
        topic_set.add(topic.strip())
    if len(topic_set) > MAX_SCOPE_TOPICS:
        raise ScopeError(f"a grant can name at most {MAX_SCOPE_TOPICS} topics")
    since, until = _utc(since, "start"), _utc(until, "end")
    if since is not None and until is not None and since >= until:
        raise ScopeError("the start of the time window must be before its end")
    return GrantScope(
        robots=tuple(robot_ids),
        topics=tuple(sorted(topic_set, key=lambda t: t.encode("utf-8"))),
        since=since,
        until=until,
    )


def scope_encode(scope: GrantScope) -> bytes:
    """The canonical bytes of a scope (module docstring)."""
    parts = [SCOPE_DOMAIN, struct.pack(">H", len(scope.robots))]
    parts += [robot.bytes for robot in sorted(scope.robots, key=lambda r: r.bytes)]
    topics = sorted(topic.encode("utf-8") for topic in scope.topics)
    parts.append(struct.pack(">H", len(topics)))
    parts += [struct.pack(">H", len(topic)) + topic for topic in topics]
    flags = (scope.since is not None) | (scope.until is not None) << 1
    parts.append(struct.pack(">BQQ", flags, _micros(scope.since) or 0, _micros(scope.until) or 0))
    return b"".join(parts)


def scope_commitment(scope: GrantScope) -> bytes:
    """What the chain holds for the scope: SM3 of its bytes; zeros for all records."""
    if scope.is_all:
        return ALL_RECORDS_COMMITMENT
    return sm3.sm3_digest(scope_encode(scope))


def expiry_seconds(expires_at: datetime | None) -> int:
    """A grant's expiry as the chain holds it: unix seconds, 0 for never."""
    if expires_at is None:
        return 0
    return int(expires_at.timestamp())


def _is_utf8(text: str) -> bool:
    """Whether the text encodes as UTF-8 (a lone surrogate from JSON's "\\ud800" does not)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _micros(moment: datetime | None) -> int | None:
    if moment is None:
        return None
    delta = moment - EPOCH
    return (delta.days * 86_400 + delta.seconds) * 1_000_000 + delta.microseconds


def _utc(moment: datetime | None, which: str) -> datetime | None:
    if moment is None:
        return None
    if moment.tzinfo is None:
        raise ScopeError(f"the {which} of the time window needs a time zone")
    moment = moment.astimezone(UTC)
    micros = _micros(moment)
    if micros < 0 or micros > MAX_UINT64:
        raise ScopeError(f"the {which} of the time window must be after 1970-01-01")
    return moment
