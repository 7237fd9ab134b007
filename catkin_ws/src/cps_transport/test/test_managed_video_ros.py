"""A raw-only camera's managed video (image_compressor with ~robot): the frames sent follow the
manager's level (shrunk to its size) and rate, the status says so, and bad settings keep the last
good ones."""

import threading

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for
from cps_transport.image_compression import camera_test_image, decode_jpeg

pytestmark = [pytest.mark.ros, pytest.mark.waiting]

ROBOT = "jackal"
CAMERA_HZ = 20.0  # the raw camera's rate in this test
# The output rate, over a WINDOW_S window of header stamps, within RATE_TOLERANCE of the set rate.
WINDOW_S = 4.0
RATE_TOLERANCE = 0.2


@pytest.fixture
def camera(ros, rospy_node):
    """image_compressor for ROBOT, fed 640x480 rgb8 frames at CAMERA_HZ until the test ends."""
    from sensor_msgs.msg import CompressedImage, Image

    from cps_msgs.msg import RateLimiterStatus

    ros.start_node("cps_transport", "image_compressor", name="image_compressor", params={"~robot": ROBOT})
    ros.wait_for_topic(names.absolute(names.robot_topic(ROBOT, names.VIDEO_STATUS)), timeout_s=20)
    raw = rospy_node.Publisher(names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE)), Image, queue_size=2)
    images = TopicRecorder(
        names.absolute(names.robot_topic(ROBOT, names.CAMERA_IMAGE_COMPRESSED)), CompressedImage, queue_size=200
    )
    status = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.VIDEO_STATUS)), RateLimiterStatus)
    rgb = camera_test_image(640, 480)
    stop = threading.Event()

    def feed():
        msg = Image(height=480, width=640, encoding="rgb8", step=640 * 3, data=rgb.tobytes())
        msg.header.frame_id = f"{ROBOT}/camera_depth_optical_frame"
        while not stop.is_set():
            msg.header.stamp = rospy_node.Time.now()
            raw.publish(msg)
            stop.wait(1.0 / CAMERA_HZ)  # the camera's frame period

    feeder = threading.Thread(target=feed, daemon=True)
    try:
        assert wait_for(lambda: raw.get_num_connections() > 0, timeout_s=10)
        feeder.start()
        yield images, status
    finally:
        stop.set()
        feeder.join(timeout=5)
        for thing in (images, status):
            thing.close()
        raw.unregister()


def _size(msg):
    return decode_jpeg(msg.data).shape[:2][::-1]


def test_raw_frames_are_shrunk_to_the_level_at_the_rate_set(camera, rospy_node):
    from std_msgs.msg import Float64, UInt8

    images, status = camera
    first = images.wait(timeout_s=20)
    assert _size(first) == (160, 120)  # the coarsest level until the manager speaks
    level = rospy_node.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.VIDEO_LEVEL)), UInt8, queue_size=1, latch=True
    )
    rate = rospy_node.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.VIDEO_RATE_HZ)), Float64, queue_size=1, latch=True
    )
    try:
        level.publish(UInt8(1))
        rate.publish(Float64(8.0))
        status.wait(lambda s: s.level == 1 and s.set_rate_hz == 8.0, timeout_s=10)
        images.wait(lambda m: _size(m) == (320, 240), timeout_s=10)
        images.take()
        images.wait_count(int(8.0 * WINDOW_S), timeout_s=WINDOW_S * 3)
        frames = [m for _, m in images.take()]
        assert all(_size(m) == (320, 240) for m in frames)
        stamps = [m.header.stamp.to_sec() for m in frames]
        measured = (len(stamps) - 1) / (stamps[-1] - stamps[0])
        assert abs(measured - 8.0) <= RATE_TOLERANCE * 8.0, f"{measured:.2f} Hz for 8 Hz"
        report = status.wait(lambda s: s.level == 1 and s.level_mean_message_bytes > 0, timeout_s=5)
        sent = sum(len(m.data) for m in frames) / len(frames)
        assert report.level_mean_message_bytes == pytest.approx(sent, rel=0.1)  # one picture: sizes alike
        assert report.level_mean_cpu_s > 0 and report.host  # issue 36: shrink + encode + publish
        rate.publish(Float64(float("nan")))
        level.publish(UInt8(9))
        images.take()
        images.wait_count(5, timeout_s=10)
        assert all(_size(m) == (320, 240) for _, m in images.take())
        report = status.wait(lambda s: s.forwarded > 0, timeout_s=5)
        assert (report.level, report.set_rate_hz) == (1, 8.0)
    finally:
        level.unregister()
        rate.unregister()
