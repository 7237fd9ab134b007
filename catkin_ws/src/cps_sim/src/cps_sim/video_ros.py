"""One camera robot's managed video as fleet_sim publishes it (rospy wiring over cps_sim.video).

Listens to the manager's <robot>/video_throttle/level (std_msgs/UInt8) and rate_hz
(std_msgs/Float64); publishes the JPEG frames on <robot>/camera/image_raw/compressed and
<robot>/video_throttle/status (cps_msgs/RateLimiterStatus, latched, 1 Hz and after every change).
"""

import threading
import time

import rospy
from sensor_msgs.msg import CompressedImage

from cps_fleet import names
from cps_msgs.msg import RateLimiterStatus
from cps_ros.publisher import Publisher
from cps_sim import messages
from cps_sim.scheduling import RateMeter
from cps_sim.video import LevelSizes, VideoTask, compressed_image_bytes
from cps_transport import host_cpu
from cps_transport.video_follower import VideoFollower

# The scheduler's key of a robot's video task (a robot's name has no space).
VIDEO_KEY_SUFFIX = " video"


def video_key(robot):
    return robot + VIDEO_KEY_SUFFIX


class RobotVideo:
    """A robot's video: the level and rate it follows, what it sent, its topics."""

    def __init__(self, robot, sensor_frame, streams, on_rate_change, unmanaged=False):
        """on_rate_change(key, rate_hz): reschedules the video task when the manager changes its rate.
        unmanaged: start at the finest level and the maximum rate (no manager will speak)."""
        self.robot, self.sensor_frame = robot, sensor_frame
        self.key = video_key(robot)
        self.lock = threading.Lock()
        self.follower = VideoFollower(robot, streams, self._on_setting, lock=self.lock)
        self.control = self.follower.control
        if unmanaged:
            self.control.set_level(0)
            self.control.set_rate(streams.video_max_rate_hz)
        self.sizes = LevelSizes(streams.video_levels)
        # Per level: what a frame cost this side, rendering (or fetching a recorded one), encoding
        # and publishing it, s (issue 36: the manager buys finer video only where the CPU exists).
        self.cpu_s = LevelSizes(streams.video_levels)
        self.host_cpu = host_cpu.shared()
        self.sent_meter = RateMeter()
        self.rendered = 0
        self.sent = 0
        self.mean_bytes = float("nan")
        self.on_rate_change = on_rate_change

        def topic(relative):
            return names.robot_topic(robot, relative)

        self.image_topic = names.absolute(topic(names.CAMERA_IMAGE_COMPRESSED))
        self.publisher = Publisher(self.image_topic, CompressedImage, queue_size=2)
        self.status_pub = Publisher(
            names.absolute(topic(names.VIDEO_STATUS)), RateLimiterStatus, queue_size=5, latch=True
        )

    @property
    def rate_hz(self):
        return self.control.rate_hz

    def _on_setting(self, rate_changed):
        if rate_changed:
            self.on_rate_change(self.key, self.control.rate_hz)
        self.publish_status()

    def wanted(self):
        """The VideoTask of the next frame, or None when nobody subscribes or the manager turned the
        video off (nothing is rendered)."""
        if self.publisher.get_num_connections() == 0:
            return None
        with self.lock:
            if self.control.off:
                return None
            level = self.control.level
            return VideoTask(self.robot, self.control.level_index, level.width, level.height, level.jpeg_quality)

    def publish(self, frame, stamp_s, now_s):
        """Send a rendered VideoFrame stamped at its pose's instant; learn its level's size."""
        msg = CompressedImage(format=frame.format, data=frame.jpeg.tobytes())
        msg.header.stamp = messages.stamp(stamp_s)
        msg.header.frame_id = self.sensor_frame
        started = time.perf_counter()
        self.publisher.publish(msg)
        cost_s = frame.render_s + frame.encode_s + time.perf_counter() - started
        size = compressed_image_bytes(msg.header.frame_id, msg.format, len(msg.data))
        with self.lock:
            self.rendered += 1
            self.sent += 1
            self.sizes.add(frame.level_index, size)
            self.cpu_s.add(frame.level_index, cost_s)
            self.mean_bytes = size if self.mean_bytes != self.mean_bytes else 0.9 * self.mean_bytes + 0.1 * size
            self.sent_meter.tick(now_s)

    def publish_status(self, now_s=None):
        now_s = time.time() if now_s is None else now_s
        idle = self.host_cpu.idle_fraction()
        with self.lock:
            index = self.control.level_index
            status = RateLimiterStatus(
                input_topic=self.image_topic,
                output_topic=self.image_topic,
                set_rate_hz=self.control.set_rate_hz,
                input_rate_hz=self.sent_meter.rate_hz(now_s),
                output_rate_hz=self.sent_meter.rate_hz(now_s),
                mean_message_bytes=self.mean_bytes,
                received=self.rendered,
                forwarded=self.sent,
                level=index,
                level_mean_message_bytes=self.sizes.mean(index),
                level_mean_cpu_s=self.cpu_s.mean(index),
                level_mean_points=float("nan"),
                host=self.host_cpu.host,
                host_cpus=self.host_cpu.cores,
                host_idle_fraction=idle,
            )
        status.header.stamp = rospy.Time.now()
        self.status_pub.publish(status)
