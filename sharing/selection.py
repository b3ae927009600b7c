"""Which records: those of some robots and some topics, captured in a time window [since, until).

One value, `RecordSelection`, wherever records are picked that way: a grant's scope
(sharing/scope.py turns it into the bytes the chain holds the commitment of), an export, a
deletion of a selection and the record lists' filters. An empty tuple of robots or topics means
all of them; no `since` or `until`, no bound on that side.

A selection someone asks for is made by `RecordSelection.of`, which holds the limits and the
checks (written here only); a filter's selection (`from_filters`) and one read back from the
database are taken as given, since a window that selects nothing is an empty list, not an error.
`covers` answers for one record in Python and `as_q`/`apply` for rows in the database, by the
same rule.
"""

import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TypeVar

from django.db.models import Q, QuerySet

# Bounds of a selection someone asks for, so that the queries it makes (and a grant's encoding
# of it) stay small.
MAX_SELECTED_ROBOTS = 100
MAX_SELECTED_TOPICS = 100
# Record.topic's column.
MAX_TOPIC_LENGTH = 255

# The rules `RecordSelection.of` holds, as SelectionError.rule names them.
BAD_ROBOT_ID = "bad_robot_id"
TOO_MANY_ROBOTS = "too_many_robots"
BAD_TOPIC = "bad_topic"
TOO_MANY_TOPICS = "too_many_topics"
NAIVE_TIME = "naive_time"
WINDOW_NOT_ORDERED = "window_not_ordered"

_Records = TypeVar("_Records", bound=QuerySet)


class SelectionError(ValueError):
    """A selection that cannot be asked for: `rule` names the rule it breaks (for a caller
    that words it its own way), the message says it in words for the owner."""

    def __init__(self, rule: str, message: str) -> None:
        super().__init__(message)
        self.rule = rule


@dataclass(frozen=True)
class RecordSelection:
    """Robots (ids) and topics (empty: all) and a capture-time window [since, until)."""

    robots: tuple[uuid.UUID, ...] = ()
    topics: tuple[str, ...] = ()
    since: datetime | None = None
    until: datetime | None = None

    @classmethod
    def of(
        cls,
        *,
        robots: Iterable[uuid.UUID | str] = (),
        topics: Iterable[str] = (),
        since: datetime | None = None,
        until: datetime | None = None,
    ) -> "RecordSelection":
        """The canonical selection of these values: robots and topics deduplicated and sorted
        (robots by their bytes, topics stripped and by their UTF-8), times in UTC.
        SelectionError for robot ids that are not UUIDs, more than MAX_SELECTED_ROBOTS robots
        or MAX_SELECTED_TOPICS topics, a topic that is not text of at most MAX_TOPIC_LENGTH
        characters, a time without a time zone, or a window that does not start before it ends.
        """
        try:
            robot_ids = sorted({uuid.UUID(str(robot)) for robot in robots}, key=lambda r: r.bytes)
        except ValueError:
            raise SelectionError(BAD_ROBOT_ID, "a robot is named by its id (a UUID)") from None
        if len(robot_ids) > MAX_SELECTED_ROBOTS:
            raise SelectionError(
                TOO_MANY_ROBOTS, f"a selection names at most {MAX_SELECTED_ROBOTS} robots"
            )
        topic_set = {_topic_checked(topic) for topic in topics}
        if len(topic_set) > MAX_SELECTED_TOPICS:
            raise SelectionError(
                TOO_MANY_TOPICS, f"a selection names at most {MAX_SELECTED_TOPICS} topics"
            )
        since, until = _utc(since, "start"), _utc(until, "end")
        if since is not None and until is not None and since >= until:
            raise SelectionError(
                WINDOW_NOT_ORDERED, "the start of the time window must be before its end"
            )
        return cls(
            robots=tuple(robot_ids),
            topics=tuple(sorted(topic_set, key=lambda t: t.encode("utf-8"))),
            since=since,
            until=until,
        )

    @classmethod
    def from_filters(
        cls,
        *,
        robot: uuid.UUID | str | None = None,
        topic: str | None = None,
        since: datetime | None = None,
        until: datetime | None = None,
    ) -> "RecordSelection":
        """The selection of a list's or a deletion's filters: one robot and one topic at most
        (None or empty: any), the window as given."""
        return cls(
            robots=(uuid.UUID(str(robot)),) if robot else (),
            topics=(topic,) if topic else (),
            since=since,
            until=until,
        )

    @property
    def is_all(self) -> bool:
        return not (self.robots or self.topics or self.since or self.until)

    def covers(self, *, robot_id: uuid.UUID | str, topic: str, captured_at: datetime) -> bool:
        """Whether a record of this robot and topic, captured then, is inside the selection."""
        if self.robots and uuid.UUID(str(robot_id)) not in self.robots:
            return False
        if self.topics and topic not in self.topics:
            return False
        if self.since is not None and captured_at < self.since:
            return False
        return self.until is None or captured_at < self.until

    def within(self, other: "RecordSelection") -> bool:
        """Whether every record this selection covers, `other` covers too (a narrowing)."""
        if other.robots and not (self.robots and set(self.robots) <= set(other.robots)):
            return False
        if other.topics and not (self.topics and set(self.topics) <= set(other.topics)):
            return False
        if other.since is not None and (self.since is None or self.since < other.since):
            return False
        return other.until is None or (self.until is not None and self.until <= other.until)

    def as_q(self) -> Q:
        """The selection as a filter of Record rows (`covers`, in the database)."""
        q = Q()
        if self.robots:
            q &= Q(robot_id__in=list(self.robots))
        if self.topics:
            q &= Q(topic__in=list(self.topics))
        if self.since is not None:
            q &= Q(captured_at__gte=self.since)
        if self.until is not None:
            q &= Q(captured_at__lt=self.until)
        return q

    def apply(self, records: _Records) -> _Records:
        """The records of the queryset (of Record) that the selection covers."""
        return records.filter(self.as_q())

    def as_json(self) -> dict[str, object]:
        """The selection as an export stores it and its proof bundle shows it (docs/export.md):
        robot ids, topics, and the window's ends in ISO 8601 UTC (null: no bound)."""
        return {
            "robots": [str(robot) for robot in self.robots],
            "topics": list(self.topics),
            "since": iso_utc(self.since),
            "until": iso_utc(self.until),
        }

    @classmethod
    def from_json(cls, value: dict) -> "RecordSelection":
        def moment(text: str | None) -> datetime | None:
            return datetime.fromisoformat(text) if text else None

        return cls(
            robots=tuple(uuid.UUID(robot) for robot in value.get("robots", [])),
            topics=tuple(value.get("topics", [])),
            since=moment(value.get("since")),
            until=moment(value.get("until")),
        )


def iso_utc(moment: datetime | None) -> str | None:
    """ISO 8601 UTC with microseconds and a Z (any year: isoformat pads it to four digits)."""
    if moment is None:
        return None
    return moment.astimezone(UTC).isoformat(timespec="microseconds").replace("+00:00", "Z")


def _topic_checked(topic: object) -> str:
    """The topic, stripped; SelectionError unless it is text of at most MAX_TOPIC_LENGTH
    characters, not blank, without NUL characters, that encodes as UTF-8."""
    if not isinstance(topic, str) or not topic.strip():
        raise SelectionError(BAD_TOPIC, "a topic cannot be empty")
    if len(topic) > MAX_TOPIC_LENGTH or "\x00" in topic or not _is_utf8(topic):
        raise SelectionError(
            BAD_TOPIC,
            f"a topic is at most {MAX_TOPIC_LENGTH} characters of text, without NUL characters",
        )
    return topic.strip()


def _is_utf8(text: str) -> bool:
    """Whether the text encodes as UTF-8 (a lone surrogate from JSON's "\\ud800" does not)."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _utc(moment: datetime | None, which: str) -> datetime | None:
    if moment is None:
        return None
    if moment.tzinfo is None:
        raise SelectionError(NAIVE_TIME, f"the {which} of the time window needs a time zone")
    return moment.astimezone(UTC)
