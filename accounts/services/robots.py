"""Robots: made with their API token (shown once, only its hash kept), the token revoked,
and how long their records are kept. Pairing a robot by its own key is pairing.py."""

import secrets
import unicodedata
from collections.abc import Sequence

from django.contrib.auth.base_user import AbstractBaseUser
from django.db import IntegrityError, transaction
from django.utils import timezone

from accounts.agent_config import Topic
from accounts.errors import InvalidRetention, InvalidRobotName, RobotNameTaken
from accounts.events import account_event_record
from accounts.models import (
    DEFAULT_TOPICS,
    RETENTION_MAX_DAYS,
    AccountEvent,
    ChainState,
    Owner,
    Robot,
    validate_robot_topics,
)
from accounts.selectors import robot_token_hash
from accounts.services.robot_keys import robot_key_revocations_release

ROBOT_TOKEN_BYTES = 32
ROBOT_NAME_MAX = 100
# Names are shown to owners (the approval page, lists, logs): control characters (CR/LF, ESC),
# invisible formatting (bidi overrides U+202A-202E and isolates U+2066-2069, zero-width marks),
# line separators, surrogates, private-use and unassigned code points could hide or disguise
# what an owner approves.
_NOT_PRINTABLE = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})


def robot_name_problem(name: str) -> str | None:
    """Why `name` (stripped) cannot name a robot, or None: 1 to 100 printable characters."""
    if not name or len(name) > ROBOT_NAME_MAX:
        return f"a robot name has 1 to {ROBOT_NAME_MAX} characters"
    for position, char in enumerate(name, start=1):
        if unicodedata.category(char) in _NOT_PRINTABLE:
            called = unicodedata.name(char, "a control character")
            return (
                f"a robot name is printable text: character {position} is U+{ord(char):04X} "
                f"({called}), a control or invisible formatting character"
            )
    return None


def robot_create(
    *, owner: Owner, name: str, topics: Sequence[Topic] | None = None
) -> tuple[Robot, str]:
    """A robot and its API token; the token is returned once and only its hash is kept.

    `topics` (default: DEFAULT_TOPICS) are kept for the robot's agent config; topics that
    are not a valid list of {name, type} raise django.core.exceptions.ValidationError.
    """
    name = name.strip()
    problem = robot_name_problem(name)
    if problem is not None:
        raise InvalidRobotName(problem)
    chosen = DEFAULT_TOPICS if topics is None else topics
    topic_list = [{"name": topic.name, "type": topic.type} for topic in chosen]
    validate_robot_topics(topic_list)
    token = secrets.token_urlsafe(ROBOT_TOKEN_BYTES)
    try:
        with transaction.atomic():
            robot = Robot.objects.create(
                owner=owner,
                name=name,
                topics=topic_list,
                token_hash=robot_token_hash(token),
                token_prefix=token[:8],
            )
    except IntegrityError:
        raise RobotNameTaken(f"{owner} already has a robot named {name!r}") from None
    return robot, token


def robot_token_revoke(*, robot: Robot, actor: AbstractBaseUser | None = None) -> Robot:
    """The robot's token stops working at once; its records stay. The owner's security page
    shows who revoked it (`actor`: the owner or an operator). A paired robot's key is revoked
    on chain, once its key is there and the records it signed are anchored (robot_keys.py)."""
    with transaction.atomic():
        revoked = Robot.objects.filter(pk=robot.pk, is_active=True).update(
            is_active=False, revoked_at=timezone.now()
        )
        if revoked:
            account_event_record(
                owner=robot.owner,
                kind=AccountEvent.Kind.ROBOT_TOKEN_REVOKED,
                actor=actor,
                detail={"robot": robot.name, "robot_id": str(robot.pk)},
            )
            keyed = Robot.objects.filter(
                pk=robot.pk, key_chain_state__in=[ChainState.PENDING, ChainState.CONFIRMED]
            )
            if keyed.update(key_revoke_state=ChainState.PENDING):
                transaction.on_commit(
                    lambda: robot_key_revocations_release(owner_id=robot.owner_id)
                )
    robot.refresh_from_db()
    return robot


def robot_retention_set(*, robot: Robot, days: int | None, actor: AbstractBaseUser) -> Robot:
    """Keep the robot's records `days` days after their capture (None: until deleted by
    hand); older ones are deleted by sharing.services.deletion.retention_apply, the beat task. The
    owner's security page shows the change."""
    if days is not None and (
        isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= RETENTION_MAX_DAYS
    ):
        raise InvalidRetention(
            f"keep records 1 to {RETENTION_MAX_DAYS} days, or leave it empty to keep them forever"
        )
    with transaction.atomic():
        before = Robot.objects.select_for_update().get(pk=robot.pk).retention_days
        if before != days:
            Robot.objects.filter(pk=robot.pk).update(retention_days=days)
            account_event_record(
                owner=robot.owner,
                kind=AccountEvent.Kind.RETENTION_SET,
                actor=actor,
                detail={
                    "robot": robot.name,
                    "before": _retention_text(before),
                    "now": _retention_text(days),
                },
            )
    robot.refresh_from_db()
    return robot


def _retention_text(days: int | None) -> str:
    return "forever" if days is None else f"{days} days"
