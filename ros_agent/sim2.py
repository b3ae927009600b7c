"""A simulated ROS 2 robot: the paper's topics published through Cyclone DDS, no ROS 2 needed.

    python -m ros_agent.sim2 [--duration SECONDS] [--odom-rate 10] [--image-rate 1] [--domain-id N]

The same trajectory and scene as the ROS 1 simulator (ros_agent.sim): /robot/odom
(nav_msgs/Odometry) and /robot/complicatedImage (sensor_msgs/Image, bgr8 320x240), as
rmw_cyclonedds publishes them (DDS topics rt/..., types pkg::msg::dds_::Type_, ROS 2's
default QoS). The start stamp is logged after `t0=` like the ROS 1 simulator's.
"""

import argparse
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from rosbags.typesys.store import Typestore

from ros_agent.dds import (
    dds_topic_name,
    domain_id_from_environment,
    idl_sample,
    idl_type,
    writer_qos,
)
from ros_agent.ros2msg import default_typestore
from ros_agent.sim import (
    IMAGE_TOPIC,
    ODOM_TOPIC,
    START_MARK,
    Pose2D,
    draw_scene,
    figure_eight,
)

logger = logging.getLogger("authros_sim2")
ODOMETRY = "nav_msgs/msg/Odometry"
IMAGE = "sensor_msgs/msg/Image"


def stamp(typestore: Any, nanoseconds: int) -> Any:
    return typestore.types["builtin_interfaces/msg/Time"](
        sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000
    )


def header(typestore: Any, nanoseconds: int, frame_id: str) -> Any:
    return typestore.types["std_msgs/msg/Header"](
        stamp=stamp(typestore, nanoseconds), frame_id=frame_id
    )


def odometry_message(typestore: Any, pose: Pose2D, nanoseconds: int) -> Any:
    """The ROS 1 simulator's odometry (ros_agent.sim.odometry_message) as a ROS 2 message."""
    t = typestore.types

    def vector(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
        return t["geometry_msgs/msg/Vector3"](x=x, y=y, z=z)

    def covariance(variance: float) -> np.ndarray:
        return np.diag([variance] * 6).astype(np.float64).reshape(36)

    pose_msg = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=pose.x, y=pose.y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(pose.yaw / 2), w=math.cos(pose.yaw / 2)
        ),
    )
    twist = t["geometry_msgs/msg/Twist"](
        linear=vector(x=pose.speed), angular=vector(z=pose.yaw_rate)
    )
    return t[ODOMETRY](
        header=header(typestore, nanoseconds, "odom"),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose_msg, covariance=covariance(0.01)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=covariance(0.001)),
    )


def image_message(typestore: Any, pixels: np.ndarray, nanoseconds: int) -> Any:
    height, width = pixels.shape[:2]
    return typestore.types[IMAGE](
        header=header(typestore, nanoseconds, "camera"),
        height=height,
        width=width,
        encoding="bgr8",
        is_bigendian=0,
        step=width * 3,
        data=np.frombuffer(pixels.tobytes(), dtype=np.uint8),
    )


class Ros2Publisher:
    """Writers for ROS 2 topics in one DDS domain, taking rosbags messages (of `typestore`'s
    types: ROS 2 Humble's by default)."""

    def __init__(self, domain_id: int, typestore: Typestore | None = None) -> None:
        from cyclonedds.domain import DomainParticipant

        self.typestore = typestore or default_typestore()
        self.participant = DomainParticipant(domain_id)
        self._writers: dict[str, tuple[Any, type]] = {}

    def writer(self, topic: str, ros2_type: str, *, best_effort: bool = False) -> None:
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic

        if topic in self._writers:
            return
        struct = idl_type(self.typestore, ros2_type)
        dds_topic = Topic(self.participant, dds_topic_name(topic), struct)
        qos = writer_qos(best_effort=best_effort)
        self._writers[topic] = (DataWriter(self.participant, dds_topic, qos=qos), struct)

    def matched(self, topic: str) -> int:
        writer, _ = self._writers[topic]
        return len(writer.get_matched_subscriptions())

    def publish(self, topic: str, msg: Any) -> None:
        writer, struct = self._writers[topic]
        writer.write(idl_sample(struct, msg))


def run(
    publisher: Ros2Publisher,
    *,
    duration: float,
    odom_rate: float,
    image_rate: float,
    stop: threading.Event,
) -> None:
    publisher.writer(ODOM_TOPIC, ODOMETRY)
    publisher.writer(IMAGE_TOPIC, IMAGE)
    start = time.time_ns()
    logger.info(
        "publishing %s at %g Hz and %s at %g Hz from stamp %s%d.%09d",
        ODOM_TOPIC,
        odom_rate,
        IMAGE_TOPIC,
        image_rate,
        START_MARK,
        start // 1_000_000_000,
        start % 1_000_000_000,
    )
    next_image, frame, period = start, 0, 1.0 / odom_rate
    ticks = 0
    while not stop.is_set():
        now = time.time_ns()
        since = now - start
        elapsed = since // 10**9 + (since % 10**9) / 1e9  # as genpy's Duration.to_sec()
        if duration and elapsed >= duration:
            break
        publisher.publish(
            ODOM_TOPIC, odometry_message(publisher.typestore, figure_eight(elapsed), now)
        )
        if now >= next_image:
            publisher.publish(
                IMAGE_TOPIC, image_message(publisher.typestore, draw_scene(frame), now)
            )
            frame += 1
            next_image += int(1e9 / image_rate)
        ticks += 1
        stop.wait(max(0.0, start / 1e9 + ticks * period - time.time()))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent.sim2", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--duration", type=float, default=0.0, help="seconds; 0 runs until stopped")
    parser.add_argument("--odom-rate", type=float, default=10.0, help="Hz (default 10)")
    parser.add_argument("--image-rate", type=float, default=1.0, help="Hz (default 1)")
    parser.add_argument("--domain-id", type=int, default=None, help="default: ROS_DOMAIN_ID or 0")
    parser.add_argument(
        "--wait-for-subscriber",
        type=float,
        default=0.0,
        help="seconds to wait for the agent's readers before publishing",
    )
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    domain = domain_id_from_environment() if args.domain_id is None else args.domain_id
    publisher = Ros2Publisher(domain)
    if args.wait_for_subscriber:
        publisher.writer(ODOM_TOPIC, ODOMETRY)
        publisher.writer(IMAGE_TOPIC, IMAGE)
        deadline = time.monotonic() + args.wait_for_subscriber
        while time.monotonic() < deadline and not (
            publisher.matched(ODOM_TOPIC) and publisher.matched(IMAGE_TOPIC)
        ):
            stop.wait(0.05)
    run(
        publisher,
        duration=args.duration,
        odom_rate=args.odom_rate,
        image_rate=args.image_rate,
        stop=stop,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
