"""Test support for the managed video on a real master: fleet_sim with one camera robot held
still (the scene is the same frame to frame), the manager's level and rate topics, and recorders
of its frames and status. Shared by test_video_ros and test_video_trace_ros."""

import contextlib
import time

from cps_fleet import names

ROBOT = "jackal"
# Measured rate: frames per second of the header stamps (the render instants) over a window of
# WINDOW_S; it must lie within RATE_TOLERANCE of the set rate (the 2-core test machine is shared).
WINDOW_S = 4.0
RATE_TOLERANCE = 0.2


@contextlib.contextmanager
def video_sim(ros_master, rospy_node, name="fleet_sim", **params):
    """(graph, level publisher, rate publisher, frames recorder, status recorder) of a fleet_sim
    running ROBOT with `params` added to its private ones; everything stopped on exit."""
    from sensor_msgs.msg import CompressedImage
    from std_msgs.msg import Bool, Float64, UInt8

    from cps_harness.testing import TopicRecorder
    from cps_msgs.msg import RateLimiterStatus

    graph = ros_master.attach()
    estop = rospy_node.Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
    estop.publish(Bool(True))  # the robot stands still: the scene is the same frame to frame
    level = rospy_node.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.VIDEO_LEVEL)), UInt8, queue_size=1, latch=True
    )
    rate = rospy_node.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.VIDEO_RATE_HZ)), Float64, queue_size=1, latch=True
    )
    images = TopicRecorder(
        names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE_COMPRESSED)), CompressedImage, queue_size=200
    )
    status = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.VIDEO_STATUS)), RateLimiterStatus)
    try:
        private = {"~profile": "light", "~robots": ROBOT, **{f"~{k}": v for k, v in params.items()}}
        graph.start_node("cps_sim", "fleet_sim", name=name, params=private)
        graph.wait_for_topic(names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE_COMPRESSED)), timeout_s=60)
        yield graph, level, rate, images, status
    finally:
        graph.close()
        for thing in (estop, level, rate, images, status):
            (thing.unregister if hasattr(thing, "unregister") else thing.close)()


def dimensions(msg):
    """(width, height) of a JPEG frame."""
    from cps_transport.image_compression import decode_jpeg

    return decode_jpeg(msg.data).shape[:2][::-1]


def stamp_rate_hz(messages):
    stamps = [m.header.stamp.to_sec() for m in messages]
    return (len(stamps) - 1) / (stamps[-1] - stamps[0])


def frames_at(images, width, window_s):
    """The frames of `width` received over `window_s` once the first of them has arrived."""
    images.wait(lambda m: dimensions(m)[0] == width, timeout_s=30, what=f"a {width}-wide frame")
    images.take()
    deadline = time.monotonic() + window_s
    frames = []
    while time.monotonic() < deadline:
        images.wait_count(len(frames) + 1, timeout_s=10)  # returns as soon as one more arrived
        frames = [m for _, m in images.messages]
    return [m for m in frames if dimensions(m)[0] == width]
