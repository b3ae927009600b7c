"""The agent on a ROS 2 robot, without a ROS 2 installation: Cyclone DDS in, the same sealing out.

    python -m ros_agent --ros2 --config agent.yaml

Each configured topic (`/robot/odom`, type `nav_msgs/Odometry`) is read as the DDS topic
`rt/robot/odom` of type `nav_msgs::msg::dds_::Odometry_` in the domain ROS_DOMAIN_ID, with a QoS
that matches ROS 2 publishers (ros_agent.dds). Samples come as CDR, rosbags decodes them
(any type of the ROS 2 type store of `ros2_distro`, or a custom one learned from its `.msg`
files, ros_agent.ros2msg; Odometry, Image, CompressedImage, Imu have the ROS 1 extractors,
everything else the generic walk), and from there it is the ROS 1 agent's path:
Recorder (seal into the spool), Uploader (to the portal). CYCLONEDDS_URI chooses the network;
ros_agent.dds writes one for this machine only. SIGINT/SIGTERM stop it like the ROS 1 agent.
"""

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ros_agent import LOGGER_NAME
from ros_agent.config import AgentConfig, ConfigError, load_config
from ros_agent.dds import (
    HISTORY_DEPTH,
    SENSOR_TYPES,
    DdsError,
    dds_topic_name,
    domain_id_from_environment,
    idl_type,
    reader_qos,
)
from ros_agent.pipeline import CLEAR_TEXT_WARNING, pipeline_build, token_in_clear
from ros_agent.ros2msg import (
    MessageTypeUnknown,
    default_typestore,
    learn_message_types,
    ros1_view,
    ros2_name,
)
from ros_agent.spool import SpoolError

logger = logging.getLogger(f"{LOGGER_NAME}.ros2")

TAKE_BATCH = 64
WAIT_SECONDS = 0.2
DISCOVERY_INTERVAL = 1.0  # seconds between looks at who publishes what


@dataclass
class TopicReader:
    """One configured topic and the DDS reader that reads it now."""

    topic: str
    ros_type: str
    ros2_type: str
    dds_topic: Any
    reader: Any
    best_effort: bool


class Ros2Agent:
    """One robot's agent on ROS 2: DDS readers -> rosbags -> Recorder -> Spool -> Uploader."""

    def __init__(self, config: AgentConfig, *, domain_id: int | None = None) -> None:
        self.config = config
        self.domain_id = domain_id_from_environment() if domain_id is None else domain_id
        self.pipeline = pipeline_build(config)
        self.counters, self.spool = self.pipeline.counters, self.pipeline.spool
        self.uploader, self.recorder = self.pipeline.uploader, self.pipeline.recorder
        self.typestore = default_typestore(config.ros2_distro)
        self.stopping = threading.Event()
        self._readers: list[TopicReader] = []
        self._publications: Any = None  # the DCPSPublication builtin topic: who publishes what
        self._participant: Any = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Check every topic's type, join the DDS domain, start reading and uploading."""
        from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        types = {}
        for topic in self.config.topics:
            ros2_type = ros2_name(topic.type)
            try:
                learned = learn_message_types(
                    self.typestore, [ros2_type], self.config.msg_search_dirs
                )
                types[topic.name] = idl_type(self.typestore, ros2_type, raw=True)
            except (MessageTypeUnknown, DdsError) as exc:
                raise DdsError(f"topic {topic.name}: {exc}") from None
            if learned:
                logger.info("learned %s from .msg files", ", ".join(learned))
        try:
            self._participant = DomainParticipant(self.domain_id)
        except Exception as exc:  # cyclonedds raises DDSException for a bad CYCLONEDDS_URI
            raise DdsError(f"Cyclone DDS cannot start in domain {self.domain_id}: {exc}") from None
        self._publications = BuiltinDataReader(self._participant, BuiltinTopicDcpsPublication)
        for topic in self.config.topics:
            ros2_type = ros2_name(topic.type)
            name = "/" + topic.name.lstrip("/~")
            dds_topic = Topic(self._participant, dds_topic_name(name), types[topic.name])
            best_effort = ros2_type in SENSOR_TYPES
            self._readers.append(
                TopicReader(
                    topic=name,
                    ros_type=topic.type,
                    ros2_type=ros2_type,
                    dds_topic=dds_topic,
                    reader=DataReader(
                        self._participant, dds_topic, qos=reader_qos(ros2_type, best_effort)
                    ),
                    best_effort=best_effort,
                )
            )
            logger.info(
                "recording %s (%s) as DDS topic %s, %s",
                name,
                topic.type,
                dds_topic_name(name),
                "best effort" if best_effort else "reliably",
            )
        if (host := token_in_clear(self.config.portal_url)) is not None:
            logger.warning(CLEAR_TEXT_WARNING, host)
        self.uploader.start()
        self._thread = threading.Thread(target=self._read, name="authros-dds", daemon=True)
        self._thread.start()
        logger.info(
            "robot %s of %s (ROS 2, domain %d) uploads to %s; spool %s (%d queued)",
            self.config.robot,
            self.config.owner,
            self.domain_id,
            self.config.records_url,
            self.spool.directory,
            len(self.spool),
        )

    def stop(self) -> None:
        logger.info("stopping: sending what is queued")
        self.stopping.set()
        if self._thread is not None:
            self._thread.join(5)
        self.recorder.close()
        self.uploader.stop(self.config.shutdown_flush)
        self.spool.close()
        self._readers.clear()
        self._publications = None
        self._participant = None
        self.log_stats()

    def log_stats(self) -> None:
        logger.info(
            "sent=%(sent)d spooled=%(spooled)d failed=%(failed)d dropped=%(dropped)d "
            "queued=%(queued)d spool_bytes=%(spool_bytes)d",
            self.pipeline.stats(),
        )

    def _read(self) -> None:
        from cyclonedds.util import duration

        waitset = self._waitset()
        next_stats = time.monotonic() + self.config.stats_interval
        next_discovery = 0.0
        while not self.stopping.is_set():
            waitset.wait(duration(seconds=WAIT_SECONDS))
            for topic_reader in self._readers:
                for sample in topic_reader.reader.take(TAKE_BATCH):
                    self._record(sample, topic_reader)
            now = time.monotonic()
            if now >= next_discovery:
                if self._adapt_to_publishers():
                    waitset = self._waitset()
                next_discovery = now + DISCOVERY_INTERVAL
            if now >= next_stats:
                self.log_stats()
                next_stats += self.config.stats_interval

    def _waitset(self) -> Any:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet

        waitset = WaitSet(self._participant)
        for topic_reader in self._readers:
            waitset.attach(
                ReadCondition(
                    topic_reader.reader, SampleState.Any | ViewState.Any | InstanceState.Any
                )
            )
        return waitset

    def _adapt_to_publishers(self) -> bool:
        """Read best effort any topic that has a best-effort publisher: a reliable reader would
        not match it (as rosbag2 adapts to the QoS publishers offer). True if a reader changed."""
        from cyclonedds.core import Policy
        from cyclonedds.sub import DataReader

        changed = False
        for publication in self._publications.take(TAKE_BATCH):
            reliability = getattr(publication, "qos", None)
            if (
                reliability is None
                or reliability[Policy.Reliability] is not Policy.Reliability.BestEffort
            ):
                continue
            for topic_reader in self._readers:
                if (
                    topic_reader.best_effort
                    or publication.topic_name != topic_reader.dds_topic.name
                ):
                    continue
                # Take what the reliable reader holds before it goes.
                for sample in topic_reader.reader.take(HISTORY_DEPTH):
                    self._record(sample, topic_reader)
                topic_reader.reader = DataReader(
                    self._participant,
                    topic_reader.dds_topic,
                    qos=reader_qos(topic_reader.ros2_type, True),
                )
                topic_reader.best_effort = changed = True
                logger.info(
                    "%s has a best-effort publisher: reading it best effort", topic_reader.topic
                )
        return changed

    def _record(self, sample: Any, topic_reader: TopicReader) -> None:
        topic, ros_type = topic_reader.topic, topic_reader.ros_type
        ros2_type = topic_reader.ros2_type
        received_at = datetime.now(UTC)
        cdr = getattr(sample, "cdr", None)
        if cdr is None:  # an instance disposed or unregistered: no data
            return
        try:
            msg = self.typestore.deserialize_cdr(cdr, ros2_type)
        except Exception as exc:  # a sample that does not decode is dropped
            failed = self.counters.add("failed")
            logger.error(
                "a %s sample on %s does not decode: %s (%d failed)", ros_type, topic, exc, failed
            )
            return
        self.recorder.record(
            ros1_view(msg), topic=topic, ros_type=ros_type, received_at=received_at
        )


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent --ros2",
        description="AuthROS agent on ROS 2 (Cyclone DDS): seal topics and upload them.",
    )
    parser.add_argument("--config", type=Path, required=True, help="agent.yaml")
    parser.add_argument(
        "--domain-id", type=int, default=None, help="DDS domain (default: ROS_DOMAIN_ID or 0)"
    )
    args = parser.parse_args(list(argv))
    try:
        config = load_config(args.config)
        agent = Ros2Agent(config, domain_id=args.domain_id)
    except (ConfigError, SpoolError, DdsError) as exc:
        print(f"authros_agent: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    try:
        agent.start()
    except DdsError as exc:
        logger.critical("%s", exc)
        agent.stop()
        return 2
    try:
        while not stop.wait(0.5):
            pass
    finally:
        agent.stop()
    return 0
