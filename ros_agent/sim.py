"""A simulated robot publishing the paper's topics, for demos and tests.

    python -m ros_agent.sim [--duration SECONDS] [--odom-rate 10] [--image-rate 1]

- /robot/odom (nav_msgs/Odometry) at 10 Hz: a figure-eight (lemniscate of Gerono, 3 m half
  width, one lap a minute) with a heading along the path, and the body-frame twist
  (forward speed, yaw rate) that matches it.
- /robot/complicatedImage (sensor_msgs/Image, bgr8, 320x240) at 1 Hz: a scene drawn with Pillow
  (colour gradient, ground grid, moving shapes, text, a patch of sensor noise whose size sets
  the PNG size). Its PNG as the agent encodes it (extractors.encode_png, Pillow 13.0.0)
  measured 57,089 to 59,482 bytes, mean 58,465 bytes (57.1 KiB), over frames 0-119: about
  the paper's 58 KB images.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, ImageDraw, ImageFont

if TYPE_CHECKING:  # ROS 1 only where it publishes: the ROS 2 simulator (sim2) uses the rest
    import genpy
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Image

ODOM_TOPIC = "/robot/odom"
IMAGE_TOPIC = "/robot/complicatedImage"
IMAGE_WIDTH = 320
IMAGE_HEIGHT = 240
NOISE_PATCH = (120, 72)  # width, height of the sensor-noise patch that sets the PNG size
NOISE_SIGMA = 6.0
LAP_SECONDS = 60.0
HALF_WIDTH = 3.0  # metres
# In the start-up log line, before the stamp the trajectory's time counts from: with it, what
# was published at any stamp can be computed again (tests compare it with what was stored).
START_MARK = "t0="


@dataclass(frozen=True)
class Pose2D:
    x: float
    y: float
    yaw: float
    speed: float  # forward, m/s
    yaw_rate: float  # rad/s


def figure_eight(t: float, *, half_width: float = HALF_WIDTH, lap: float = LAP_SECONDS) -> Pose2D:
    """Where the robot is at time t on x = A sin(wt), y = A sin(wt) cos(wt)."""
    w = 2 * math.pi / lap
    a = half_width
    s, c = math.sin(w * t), math.cos(w * t)
    s2, c2 = math.sin(2 * w * t), math.cos(2 * w * t)
    dx, dy = a * w * c, a * w * c2
    ddx, ddy = -a * w * w * s, -2 * a * w * w * s2
    speed_squared = dx * dx + dy * dy  # never zero: cos(wt) and cos(2wt) do not vanish together
    return Pose2D(
        x=a * s,
        y=a * s * c,
        yaw=math.atan2(dy, dx),
        speed=math.sqrt(speed_squared),
        yaw_rate=(dx * ddy - dy * ddx) / speed_squared,
    )


def draw_scene(frame: int) -> np.ndarray:
    """A 320x240 BGR scene that changes with every frame."""
    h, w = IMAGE_HEIGHT, IMAGE_WIDTH
    x = np.linspace(0.0, 1.0, w, dtype=np.float32)
    y = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
    phase = frame * 0.07
    scene = np.empty((h, w, 3), np.uint8)
    scene[..., 0] = (255 * (0.5 + 0.5 * np.sin(2 * np.pi * (x + phase))) * (1 - y)).astype(np.uint8)
    scene[..., 1] = (200 * y + 40 * x).astype(np.uint8)
    scene[..., 2] = np.clip(255 * x * (1 - y) + 60, 0, 255).astype(np.uint8)
    ground = h * 3 // 4
    scene[ground:] = (60, 70, 60)
    # drawn in RGB by Pillow (colours below are BGR, as the scene is), then back to BGR
    canvas = Image.fromarray(np.ascontiguousarray(scene[..., ::-1]))
    draw = ImageDraw.Draw(canvas)

    def rgb(bgr: tuple[int, int, int]) -> tuple[int, int, int]:
        return bgr[2], bgr[1], bgr[0]

    for column in range(-w, 2 * w, 40):
        draw.line([(w // 2, ground), (column, h - 1)], fill=rgb((110, 120, 110)), width=1)
    angle = frame * 0.3
    orbit = (int(w / 2 + 90 * math.cos(angle)), int(h / 2 - 20 + 50 * math.sin(angle)))
    draw.ellipse(
        [orbit[0] - 24, orbit[1] - 24, orbit[0] + 24, orbit[1] + 24], fill=rgb((40, 40, 220))
    )
    corner = (int(40 + 30 * math.sin(angle * 0.7)), 40)
    draw.rectangle([corner, (corner[0] + 60, corner[1] + 40)], fill=rgb((220, 160, 30)))
    triangle = [(200 + 20 * math.cos(angle), 150), (240, 110 + 10 * math.sin(angle)), (280, 150)]
    draw.polygon([(int(x), int(y)) for x, y in triangle], fill=rgb((30, 200, 230)))
    draw.text((8, h - 24), f"AuthROS sim frame {frame}", fill=(255, 255, 255), font=_font())
    scene = np.asarray(canvas)[..., ::-1].copy()
    patch_w, patch_h = NOISE_PATCH
    rng = np.random.default_rng(frame)
    patch = scene[:patch_h, w - patch_w :].astype(np.float32)
    patch += rng.normal(0.0, NOISE_SIGMA, patch.shape).astype(np.float32)
    scene[:patch_h, w - patch_w :] = np.clip(patch, 0, 255).astype(np.uint8)
    return scene


@cache
def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=14)


def odometry_message(pose: Pose2D, stamp: genpy.Time) -> Odometry:
    from nav_msgs.msg import Odometry

    msg = Odometry()
    msg.header.stamp = stamp
    msg.header.frame_id = "odom"
    msg.child_frame_id = "base_link"
    msg.pose.pose.position.x = pose.x
    msg.pose.pose.position.y = pose.y
    msg.pose.pose.orientation.z = math.sin(pose.yaw / 2)
    msg.pose.pose.orientation.w = math.cos(pose.yaw / 2)
    msg.pose.covariance = _diagonal_covariance(0.01)
    msg.twist.twist.linear.x = pose.speed
    msg.twist.twist.angular.z = pose.yaw_rate
    msg.twist.covariance = _diagonal_covariance(0.001)
    return msg


def image_message(pixels: np.ndarray, stamp: genpy.Time) -> Image:
    from sensor_msgs.msg import Image

    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = "camera"
    msg.height, msg.width = pixels.shape[:2]
    msg.encoding = "bgr8"
    msg.is_bigendian = 0
    msg.step = msg.width * 3
    msg.data = pixels.tobytes()
    return msg


def run(*, duration: float, odom_rate: float, image_rate: float) -> None:
    """Publish until rospy shuts down or `duration` seconds (0: forever) have passed."""
    import rospy  # here, not at the top: importing rospy registers an atexit hook that logs
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import Image

    odom_pub = rospy.Publisher(ODOM_TOPIC, Odometry, queue_size=10)
    image_pub = rospy.Publisher(IMAGE_TOPIC, Image, queue_size=2)
    start = rospy.Time.now()
    image_every = rospy.Duration(1.0 / image_rate)
    next_image = start
    rate = rospy.Rate(odom_rate)
    frame = 0  # rospy numbers header.seq itself, so the frame number is kept here
    rospy.loginfo(
        "publishing %s at %g Hz and %s at %g Hz from stamp %s%d.%09d",
        ODOM_TOPIC,
        odom_rate,
        IMAGE_TOPIC,
        image_rate,
        START_MARK,
        start.secs,
        start.nsecs,
    )
    while not rospy.is_shutdown():
        now = rospy.Time.now()
        elapsed = (now - start).to_sec()
        if duration and elapsed >= duration:
            break
        odom_pub.publish(odometry_message(figure_eight(elapsed), now))
        if now >= next_image:
            image_pub.publish(image_message(draw_scene(frame), now))
            frame += 1
            next_image += image_every
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


def main(argv: Sequence[str] | None = None) -> int:
    import rospy

    argv = rospy.myargv(list(sys.argv if argv is None else argv))
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent.sim", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--duration", type=float, default=0.0, help="seconds; 0 runs until stopped")
    parser.add_argument("--odom-rate", type=float, default=10.0, help="Hz (default 10)")
    parser.add_argument("--image-rate", type=float, default=1.0, help="Hz (default 1)")
    args = parser.parse_args(argv[1:])
    rospy.init_node("authros_sim", anonymous=True)
    run(duration=args.duration, odom_rate=args.odom_rate, image_rate=args.image_rate)
    return 0


def _diagonal_covariance(variance: float) -> list[float]:
    return [variance if row == column else 0.0 for row in range(6) for column in range(6)]


if __name__ == "__main__":
    sys.exit(main())
