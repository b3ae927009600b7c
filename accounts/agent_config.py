"""The portal's side of the agent's settings file (agent.yaml): topics and their checks, and
the file the portal writes for a robot.

The agent (ros_agent/config.py) reads the same format. The two sides share no code, only the
format: tests run one table of topic values through both parsers and load what the portal
writes with the agent's own loader, so that a robot's config never fails where it runs.
Nothing here needs Django's settings or the database.
"""

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime

import yaml
from django.utils.text import slugify

# The agent's rules, to the character (ros_agent/config.py, _ROS_TYPE and _TOPIC_NAME).
_ROS_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/[A-Za-z][A-Za-z0-9_]*")
_TOPIC_NAME = re.compile(r"~?/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*")
# The agent reads the token from this file when the config does not hold it.
TOKEN_FILENAME = "robot.token"  # noqa: S105 (a file name)


class InvalidTopics(ValueError):
    """Topics the agent would refuse; the message says which entry and why."""


@dataclass(frozen=True)
class Topic:
    """One topic a robot's agent subscribes to: its name and its ROS message type."""

    name: str
    type: str


# The topics of ros_agent.sim (and of the paper): odometry and a camera.
DEFAULT_TOPICS = (
    Topic(name="/robot/odom", type="nav_msgs/Odometry"),
    Topic(name="/robot/complicatedImage", type="sensor_msgs/Image"),
)


def topics_parse(value: object) -> tuple[Topic, ...]:
    """Topics as agent.yaml lists them ([{name, type}, ...]), checked as the agent checks
    them, with the agent's messages; raises InvalidTopics."""
    if isinstance(value, list) and not value:
        raise InvalidTopics("List at least one topic.")
    if not isinstance(value, list):
        raise InvalidTopics("topics must be a list of {name, type} entries")
    topics = []
    for index, entry in enumerate(value):
        where = f"topics[{index}]"
        if not isinstance(entry, Mapping) or set(entry) != {"name", "type"}:
            raise InvalidTopics(f"{where} must have exactly the keys name and type, got {entry!r}")
        name, ros_type = entry["name"], entry["type"]
        if not isinstance(name, str) or not _TOPIC_NAME.fullmatch(name):
            raise InvalidTopics(f"{where}: {name!r} is not a valid ROS topic name")
        if not isinstance(ros_type, str) or not _ROS_TYPE.fullmatch(ros_type):
            raise InvalidTopics(
                f"{where}: type {ros_type!r} must be package/Message, e.g. nav_msgs/Odometry"
            )
        topics.append(Topic(name=name, type=ros_type))
    names = [topic.name for topic in topics]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise InvalidTopics(f"topics listed twice: {', '.join(duplicates)}")
    return tuple(topics)


def topics_as_list(topics: Sequence[Topic]) -> list[dict[str, str]]:
    """Topics as agent.yaml (and the robot's stored row) lists them."""
    return [{"name": topic.name, "type": topic.type} for topic in topics]


def config_filename(robot_name: str) -> str:
    return f"agent-{slugify(robot_name) or 'robot'}.yaml"


def key_filename(owner_username: str) -> str:
    return f"{slugify(owner_username) or 'owner'}.sm4"


def agent_config_yaml(
    *,
    portal_url: str,
    robot_id: str,
    robot_name: str,
    owner_username: str,
    topics: Sequence[Topic],
    token: str | None,
    made_at: datetime,
    key_file: str | None = None,
    options: Mapping[str, object] | None = None,
) -> str:
    """An agent.yaml for a robot; it holds `token` if given, else names TOKEN_FILENAME.

    Never the SM4 key itself: the file names a key file the owner fills in (`key_file`, by
    default named after the owner). `options` are the agent's optional settings (batch_size,
    spool_dir, ...), written as given after the topics.
    """
    key_file = key_file or key_filename(owner_username)
    settings_map: dict[str, object] = {
        "portal_url": portal_url.rstrip("/"),
        "robot": robot_id,
        "owner": owner_username,
    }
    if token is None:
        settings_map["token_file"] = TOKEN_FILENAME
    else:
        settings_map["token"] = token
    settings_map["key_file"] = key_file
    settings_map["topics"] = topics_as_list(topics)
    settings_map.update(options or {})
    token_line = (
        "# It holds the robot's API token: keep it private too (chmod 600 this file)."
        if token
        else f"# Put the robot's API token (shown once when the robot was added) in "
        f"{TOKEN_FILENAME}, mode 0600."
    )
    header = "\n".join(
        [
            f"# AuthROS agent settings for robot {robot_name!r} of {owner_username}, "
            f"made {made_at:%Y-%m-%d %H:%M} UTC.",
            "# Run it with: python -m ros_agent --config agent.yaml",
            token_line,
            "# The SM4 key is not in this file. Put your key (32 hex digits) in the key file",
            f"# named below, beside this file, readable by you only: chmod 600 {key_file}",
        ]
    )
    body = yaml.safe_dump(settings_map, sort_keys=False, default_flow_style=False)
    return f"{header}\n{body}"
