"""Is a robot alive, and what is it sending: what the robot page and its status poll read.

`robot_activity` is one cheap read per question, whatever the robot has stored: its newest
upload (the robot row's `last_upload_at`, set with every upload) and newest capture (one index
seek), and the messages per topic over the last minute and hour, each one aggregate query over
the index record_robot_captured_topic (robot, capture time, topic, type: the scan reads the
index alone, never the rows), the hour's reused for a minute. `robot_latest_anchored` picks
the records the page shows integrity-checked: the newest anchored pose and image, by one index
seek per ROS type.

Rates are by capture time, the time the robot gives its messages; a robot's clock ahead of the
portal's is no reason to drop its newest messages, so the windows have no upper end.
"""

import uuid
from contextlib import suppress
from dataclasses import dataclass, field
from datetime import datetime, timedelta

from django.core.cache import cache
from django.db.models import Count, Max
from redis.exceptions import RedisError

from accounts.models import Owner, Robot
from sharing.content import IMAGE_TYPES, ODOMETRY
from sharing.models import Record

MINUTE = timedelta(minutes=1)
HOUR = timedelta(hours=1)
# How long the hour's counts of a robot are reused (measured in bench/REPORT.md: the hour of a
# robot at 12 messages a second is 43,200 index entries, the minute's 720).
HOUR_COUNTS_SECONDS = 60


@dataclass(frozen=True)
class TopicRate:
    """Messages of one topic (and ROS type) captured over the last minute and the last hour."""

    topic: str
    data_type: str
    last_minute: int
    last_hour: int
    # What the hour's rate is over: the hour, or less for a robot added within it (issue 48).
    hour_seconds: float = HOUR.total_seconds()

    @property
    def per_second_minute(self) -> float:
        return self.last_minute / MINUTE.total_seconds()

    @property
    def per_second_hour(self) -> float:
        return self.last_hour / self.hour_seconds


@dataclass(frozen=True)
class RobotActivity:
    robot: Robot
    now: datetime
    last_upload_at: datetime | None  # when the portal received its newest upload
    last_captured_at: datetime | None  # the newest capture time it sent
    topics: list[TopicRate] = field(default_factory=list)
    hour_seconds: float = HOUR.total_seconds()

    @property
    def hour_label(self) -> str:
        """The hour's column in words: "Last hour", or since when for a younger robot."""
        if self.hour_seconds >= HOUR.total_seconds():
            return "Last hour"
        return f"Last {self.hour_seconds / 60:.0f} min (since it was added)"

    @property
    def last_seen_at(self) -> datetime | None:
        """When the robot was last heard of: its newest upload, else its newest capture."""
        return self.last_upload_at or self.last_captured_at


def robot_of_owner(owner: Owner, robot_id: uuid.UUID | str) -> Robot | None:
    """The owner's robot with this id; None for anyone else's, as for one that does not exist."""
    try:
        wanted = uuid.UUID(str(robot_id))
    except ValueError:
        return None
    return Robot.objects.filter(pk=wanted, owner=owner).first()


def robot_activity(robot: Robot, *, now: datetime) -> RobotActivity:
    """The robot's newest upload and capture, and its messages per topic over the last minute
    and hour (topics with nothing in the last hour are not listed), busiest first.

    The minute's counts are read at every call; the hour's, 60 times as many index entries,
    at most once in HOUR_COUNTS_SECONDS per robot (kept in the shared cache): an hour's count
    may be that much older than the minute's.
    """
    newest = Record.objects.filter(robot=robot).aggregate(newest=Max("captured_at"))["newest"]
    minute = _counts_since(robot, now - MINUTE)
    hour = _hour_counts(robot, now)
    # A robot added within the hour has sent for less than it: its rate is over that time.
    age = (now - robot.created_at).total_seconds() if robot.created_at else HOUR.total_seconds()
    span = min(HOUR.total_seconds(), max(MINUTE.total_seconds(), age))
    rates = []
    for topic, data_type in {*minute, *hour}:
        in_minute = minute.get((topic, data_type), 0)
        # The hour's counts may be a minute old: never fewer than the minute's.
        in_hour = max(hour.get((topic, data_type), 0), in_minute)
        rates.append(TopicRate(topic, data_type, in_minute, in_hour, span))
    topics = sorted(rates, key=lambda rate: (-rate.last_minute, -rate.last_hour, rate.topic))
    return RobotActivity(robot, now, robot.last_upload_at, newest, topics, span)


def _counts_since(robot: Robot, since: datetime) -> dict[tuple[str, str], int]:
    """Messages per (topic, type) captured since then: one aggregate over the covering index."""
    rows = (
        Record.objects.filter(robot=robot, captured_at__gte=since)
        .order_by()
        .values("topic", "data_type")
        # COUNT(*), not of the id: the id is not in the index, and counting it reads each row.
        .annotate(count=Count("*"))
    )
    return {(row["topic"], row["data_type"]): row["count"] for row in rows}


def _hour_counts(robot: Robot, now: datetime) -> dict[tuple[str, str], int]:
    """_counts_since an hour ago, kept HOUR_COUNTS_SECONDS in the cache shared by every web
    process; read from the database when the cache cannot answer."""
    key = f"robot-rates-hour:{robot.pk}"
    with suppress(RedisError):
        cached = cache.get(key)
        if cached is not None:
            return {(topic, data_type): count for topic, data_type, count in cached}
    counts = _counts_since(robot, now - HOUR)
    with suppress(RedisError):
        cache.set(key, [[*pair, count] for pair, count in counts.items()], HOUR_COUNTS_SECONDS)
    return counts


def robot_latest_anchored(robot: Robot, *, data_types: frozenset[str] | set[str]) -> Record | None:
    """The robot's newest anchored record of these ROS types that is not deleted: the newest one
    whose integrity can be checked now. One seek per type in the index record_robot_type_captured
    (from the newest back, past the few records still pending)."""
    newest = [
        Record.objects.filter(
            robot=robot,
            data_type=data_type,
            status=Record.Status.ANCHORED,
        )
        .live()
        .select_related("owner", "robot")
        .order_by("-captured_at", "-seq")
        .first()
        for data_type in sorted(data_types)
    ]
    found = [record for record in newest if record is not None]
    return max(found, key=lambda record: (record.captured_at, record.seq), default=None)


def robot_latest_pose_record(robot: Robot) -> Record | None:
    return robot_latest_anchored(robot, data_types={ODOMETRY})


def robot_latest_image_record(robot: Robot) -> Record | None:
    return robot_latest_anchored(robot, data_types=IMAGE_TYPES)
