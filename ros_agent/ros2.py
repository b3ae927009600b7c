"""The agent on a ROS 2 robot, without a ROS 2 installation: Cyclone DDS in, the same sealing out.

    python -m ros_agent --ros2 --config agent.yaml

Each configured topic (`/robot/odom`, type `nav_msgs/Odometry`) is read as the DDS topic
`rt/robot/odom` of type `nav_msgs::msg::dds_::Odometry_` in the domain ROS_DOMAIN_ID, with a QoS
that matches ROS 2 publishers (ros_agent.dds). Samples come as CDR, rosbags decodes them
(any type of its ROS 2 type store; Odometry, Image, CompressedImage, Imu have the ROS 1
extractors, everything else the generic walk), and from there it is the ROS 1 agent's path:
Recorder (seal into the spool), Uploader (to the portal). CYCLONEDDS_URI chooses the network;
ros_agent.dds writes one for this machine only. SIGINT/SIGTERM stop it like the ROS 1 agent.
"""

import argparse
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from ros_agent import LOGGER_NAME
from ros_agent.config import AgentConfig, ConfigError, load_config
from ros_agent.counters import AgentCounters
from ros_agent.dds import (
    DdsError,
    dds_topic_name,
    domain_id_from_environment,
    idl_type,
    reader_qos,
)
from ros_agent.ros2msg import default_typestore, ros1_view, ros2_name
from ros_agent.spool import Spool, SpoolError
from ros_agent.uploader import PortalClient, Uploader
from ros_agent.wrapping import Recorder

logger = logging.getLogger(f"{LOGGER_NAME}.ros2")

TAKE_BATCH = 64
WAIT_SECONDS = 0.2


class Ros2Agent:
    """One robot's agent on ROS 2: DDS readers -> rosbags -> Recorder -> Spool -> Uploader."""

    def __init__(self, config: AgentConfig, *, domain_id: int | None = None) -> None:
        self.config = config
        self.domain_id = domain_id_from_environment() if domain_id is None else domain_id
        self.counters = AgentCounters()
        self.spool = Spool(config.spool_dir, max_bytes=config.spool_max_bytes)
        self.uploader = Uploader(
            spool=self.spool,
            client=PortalClient(
                records_url=config.records_url,
                token=config.token,
                tls_verify=config.tls_verify,
                timeout=config.request_timeout,
            ),
            counters=self.counters,
            batch_size=config.batch_size,
            batch_max_bytes=config.batch_max_bytes,
            flush_interval=config.flush_interval,
            backoff_max=config.backoff_max,
        )
        self.recorder = Recorder(
            spool=self.spool,
            key=config.key,
            owner=config.owner,
            robot=config.robot,
            counters=self.counters,
            on_spooled=self.uploader.notify,
        )
        self.typestore = default_typestore()
        self.stopping = threading.Event()
        self._readers: list[tuple[Any, str, str, str]] = []  # reader, topic, type, ROS 2 type
        self._participant: Any = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Check every topic's type, join the DDS domain, start reading and uploading."""
        from cyclonedds.domain import DomainParticipant
        from cyclonedds.sub import DataReader
        from cyclonedds.topic import Topic

        types = {}
        for topic in self.config.topics:
            ros2_type = ros2_name(topic.type)
            try:
                types[topic.name] = idl_type(self.typestore, ros2_type, raw=True)
            except DdsError as exc:
                raise DdsError(f"topic {topic.name}: {exc}") from None
        try:
            self._participant = DomainParticipant(self.domain_id)
        except Exception as exc:  # cyclonedds raises DDSException for a bad CYCLONEDDS_URI
            raise DdsError(f"Cyclone DDS cannot start in domain {self.domain_id}: {exc}") from None
        for topic in self.config.topics:
            ros2_type = ros2_name(topic.type)
            name = "/" + topic.name.lstrip("/~")
            dds_topic = Topic(self._participant, dds_topic_name(name), types[topic.name])
            reader = DataReader(self._participant, dds_topic, qos=reader_qos(ros2_type))
            self._readers.append((reader, name, topic.type, ros2_type))
            logger.info("recording %s (%s) as DDS topic %s", name, topic.type, dds_topic_name(name))
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

    def stats(self) -> dict[str, int]:
        return {
            **self.counters.snapshot(),
            "queued": len(self.spool),
            "spool_bytes": self.spool.used_bytes,
        }

    def stop(self) -> None:
        logger.info("stopping: sending what is queued")
        self.stopping.set()
        if self._thread is not None:
            self._thread.join(5)
        self.recorder.close()
        self.uploader.stop(self.config.shutdown_flush)
        self.spool.close()
        self._readers.clear()
        self._participant = None
        self.log_stats()

    def log_stats(self) -> None:
        logger.info(
            "sent=%(sent)d spooled=%(spooled)d failed=%(failed)d dropped=%(dropped)d "
            "queued=%(queued)d spool_bytes=%(spool_bytes)d",
            self.stats(),
        )

    def _read(self) -> None:
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.util import duration

        waitset = WaitSet(self._participant)
        for reader, *_ in self._readers:
            waitset.attach(
                ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any)
            )
        next_stats = datetime.now(UTC).timestamp() + self.config.stats_interval
        while not self.stopping.is_set():
            waitset.wait(duration(seconds=WAIT_SECONDS))
            for reader, topic, ros_type, ros2_type in self._readers:
                for sample in reader.take(TAKE_BATCH):
                    self._record(sample, topic, ros_type, ros2_type)
            if datetime.now(UTC).timestamp() >= next_stats:
                self.log_stats()
                next_stats += self.config.stats_interval

    def _record(self, sample: Any, topic: str, ros_type: str, ros2_type: str) -> None:
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
