"""The rospy node: subscribe the configured topics and seal, spool and upload every message.

    python -m ros_agent --config agent.yaml
    python -m ros_agent pair --portal URL --name NAME [--dir DIR]   # see ros_agent.pairing
    python -m ros_agent _portal_url:=http://127.0.0.1:8000 _token:=... _robot:=... \\
        _owner:=alice _key_file:=/etc/authros/alice.sm4 \\
        _topics:="[{name: /robot/odom, type: nav_msgs/Odometry}]"

Without --config the settings are the node's private ROS parameters (see ros_agent.config).
SIGINT/SIGTERM (rospy's handlers) end the spin; the agent then stops recording, sends what it
can within `shutdown_flush` seconds, and leaves the rest in the spool for the next start.
"""

import argparse
import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import roslib.message
import rospy

from ros_agent import LOGGER_NAME
from ros_agent.config import AgentConfig, ConfigError, config_from_ros_params, load_config
from ros_agent.pipeline import CLEAR_TEXT_WARNING, pipeline_build, token_in_clear
from ros_agent.spool import SpoolError

NODE_NAME = "authros_agent"
LOGGER = LOGGER_NAME.removeprefix("rosout.")  # rospy.loginfo(..., logger_name=LOGGER)
SUBSCRIBER_QUEUE = 100
SUBSCRIBER_BUFFER = 16 * 1024 * 1024  # rospy's 64 KB default delays large images


class AgentError(RuntimeError):
    """The agent cannot start (e.g. a configured message type is not installed)."""


class Agent:
    """One robot's agent: subscribers -> Recorder -> Spool -> Uploader -> portal (the parts
    ros_agent.pipeline builds for every agent)."""

    def __init__(self, config: AgentConfig) -> None:
        self.config = config
        self.pipeline = pipeline_build(config)
        self.counters, self.spool = self.pipeline.counters, self.pipeline.spool
        self.uploader, self.recorder = self.pipeline.uploader, self.pipeline.recorder
        self._subscribers: list[rospy.Subscriber] = []
        self._timer: rospy.Timer | None = None

    def start(self) -> None:
        classes = [message_class(topic.type) for topic in self.config.topics]
        _warn_if_token_in_clear(self.config.portal_url)
        self.uploader.start()
        for topic, cls in zip(self.config.topics, classes, strict=True):
            resolved = rospy.resolve_name(topic.name)
            self._subscribers.append(
                rospy.Subscriber(
                    topic.name,
                    cls,
                    self._on_message,
                    callback_args=(resolved, topic.type),
                    queue_size=SUBSCRIBER_QUEUE,
                    buff_size=SUBSCRIBER_BUFFER,
                )
            )
            rospy.loginfo("recording %s (%s)", resolved, topic.type, logger_name=LOGGER)
        self._timer = rospy.Timer(rospy.Duration(self.config.stats_interval), self._log_stats)
        rospy.loginfo(
            "robot %s of %s uploads to %s; spool %s (%d queued)",
            self.config.robot,
            self.config.owner,
            self.config.records_url,
            self.spool.directory,
            len(self.spool),
            logger_name=LOGGER,
        )

    def stats(self) -> dict[str, int]:
        """The counters, plus what waits in the spool."""
        return self.pipeline.stats()

    def stop(self) -> None:
        rospy.loginfo("stopping: sending what is queued", logger_name=LOGGER)
        if self._timer is not None:
            self._timer.shutdown()
        for subscriber in self._subscribers:
            subscriber.unregister()
        self.recorder.close()
        self.uploader.stop(self.config.shutdown_flush)
        self.spool.close()
        self._log_stats()

    def _on_message(self, msg: Any, topic_and_type: tuple[str, str]) -> None:
        topic, ros_type = topic_and_type
        self.recorder.record(msg, topic=topic, ros_type=ros_type, received_at=datetime.now(UTC))

    def _log_stats(self, _event: Any = None) -> None:
        rospy.loginfo(
            "sent=%(sent)d spooled=%(spooled)d failed=%(failed)d dropped=%(dropped)d "
            "queued=%(queued)d spool_bytes=%(spool_bytes)d",
            self.stats(),
            logger_name=LOGGER,
        )


def message_class(ros_type: str) -> type:
    """The Python class of a ROS message type such as nav_msgs/Odometry."""
    try:
        cls = roslib.message.get_message_class(ros_type)
    except (ValueError, ImportError) as exc:
        raise AgentError(f"cannot load the message type {ros_type}: {exc}") from None
    if cls is None:
        package = ros_type.split("/", 1)[0]
        raise AgentError(
            f"unknown message type {ros_type}: is the Python package {package} installed "
            f"(Debian: python3-{package.replace('_', '-')})?"
        )
    return cls


def main(argv: Sequence[str] | None = None) -> int:
    argv = rospy.myargv(list(sys.argv if argv is None else argv))
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent",
        description="AuthROS agent: seal ROS topics and upload them to the portal.",
        epilog="Without --config, settings are read from the node's private ROS parameters. "
        "`python -m ros_agent pair --help`: pair a robot with its owner (writes agent.yaml).",
    )
    parser.add_argument("--config", type=Path, help="agent.yaml (see ros_agent.config)")
    args = parser.parse_args(argv[1:])
    config = None
    if args.config is not None:
        try:
            config = load_config(args.config)
        except ConfigError as exc:
            print(f"{NODE_NAME}: {exc}", file=sys.stderr)
            return 2
    rospy.init_node(NODE_NAME, anonymous=True)
    try:
        agent = Agent(config or config_from_ros_params())
    except (ConfigError, SpoolError) as exc:
        rospy.logfatal("%s", exc, logger_name=LOGGER)
        return 2
    try:
        agent.start()
    except AgentError as exc:
        rospy.logfatal("%s", exc, logger_name=LOGGER)
        agent.stop()
        return 2
    try:
        rospy.spin()
    finally:
        agent.stop()
    return 0


def _warn_if_token_in_clear(portal_url: str) -> None:
    host = token_in_clear(portal_url)
    if host is not None:
        rospy.logwarn(CLEAR_TEXT_WARNING, host, logger_name=LOGGER)
