"""A robot's managed video settings as the bandwidth manager sets them (rospy wiring over
video_levels.VideoControl), shared by the simulated camera (cps_sim.video_ros) and the raw-image
compressor (tissue.ManagedVideoCompressor)."""

import threading

import rospy
from std_msgs.msg import Float64, UInt8

from cps_fleet import names
from cps_transport.video_levels import VideoControl


class VideoFollower:
    """Subscribes `<robot>/video_throttle/level` and `rate_hz` and keeps the last good setting in
    `control` (a bad one is logged and refused); after each setting that changed something calls
    `on_change(rate_changed)` outside the lock (a setpoint repeated is not news: no status echo, no
    reschedule; issue 36)."""

    def __init__(self, robot, streams, on_change, lock=None):
        self.control = VideoControl(streams)
        self.lock = lock or threading.Lock()
        self.on_change = on_change
        self.level_topic = names.absolute(names.robot_topic(robot, names.VIDEO_LEVEL))
        self.rate_topic = names.absolute(names.robot_topic(robot, names.VIDEO_RATE_HZ))
        self.subscribers = [
            rospy.Subscriber(self.level_topic, UInt8, self._on_level, queue_size=5),
            rospy.Subscriber(self.rate_topic, Float64, self._on_rate, queue_size=5),
        ]

    def _on_level(self, msg):
        with self.lock:
            before = self.control.level_index
            error = self.control.set_level(msg.data)
            changed = self.control.level_index != before
        if error:
            rospy.logerr(f"{self.level_topic}: {error}")
            return
        if changed:
            self.on_change(False)

    def _on_rate(self, msg):
        with self.lock:
            before = (self.control.rate_hz, self.control.off)
            error, note = self.control.set_rate(msg.data)
            changed = (self.control.rate_hz, self.control.off) != before
        if error:
            rospy.logerr(f"{self.rate_topic}: {error}")
            return
        if note:
            rospy.logwarn_throttle(10.0, f"{self.rate_topic}: {note}")
        if changed:
            self.on_change(True)
