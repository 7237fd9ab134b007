"""The image_compressor node: encodes only while someone listens, keeps stamp and frame, counts
and survives encodings it does not handle, honours its rate cap and refuses bad parameters."""

import threading
import time

import pytest

from cps_fleet import names
from cps_harness.testing import wait_for
from cps_transport.image_compression import camera_test_image, decode_jpeg, psnr_db

pytestmark = [pytest.mark.ros, pytest.mark.waiting]


def _reported(diagnostics, node):
    """The newest counters the node reported on /diagnostics, as a dict of str."""
    for array in reversed(diagnostics):
        for status in array.status:
            if status.name == node:
                return {kv.key: kv.value for kv in status.values}
    return {}


def _image(rospy, encoding="rgb8", width=320, height=240):
    from sensor_msgs.msg import Image

    rgb = camera_test_image(width, height)
    msg = Image(height=height, width=width, encoding=encoding, step=width * 3, data=rgb.tobytes())
    msg.header.frame_id = "ic1/camera_optical_frame"
    msg.header.stamp = rospy.Time.now()
    return msg, rgb


def test_compressor_is_lazy_counts_bad_encodings_and_delivers_the_next_image(ros, rospy_node):
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CompressedImage, Image

    ros.start_node(
        "cps_transport",
        "image_compressor",
        name="image_compressor",
        namespace="/ic1/camera",
        params={"~jpeg_quality": 80},
        remap={"~input": names.absolute(names.robot_topic("ic1", names.CAMERA_IMAGE))},
    )
    ros.wait_for_topic(names.absolute(names.robot_topic("ic1", names.CAMERA_IMAGE_COMPRESSED)), timeout_s=20)
    diagnostics = []
    diag_sub = rospy.Subscriber(names.DIAGNOSTICS, DiagnosticArray, diagnostics.append)
    raw_pub = rospy.Publisher(names.absolute(names.robot_topic("ic1", names.CAMERA_IMAGE)), Image, queue_size=10)
    received, got = [], threading.Event()
    out_sub = None
    try:
        assert wait_for(lambda: raw_pub.get_num_connections() > 0)
        # Nobody listens to the output: frames arrive and none is encoded.
        for _ in range(5):
            raw_pub.publish(_image(rospy)[0])
            time.sleep(0.05)
        assert wait_for(
            lambda: int(_reported(diagnostics, "/ic1/camera/image_compressor").get("skipped_no_subscriber", 0)) == 5
        ), _reported(diagnostics, "/ic1/camera/image_compressor")
        assert _reported(diagnostics, "/ic1/camera/image_compressor")["processed"] == "0"

        def on_compressed(msg):
            received.append(msg)
            got.set()

        out_sub = rospy.Subscriber(
            names.absolute(names.robot_topic("ic1", names.CAMERA_IMAGE_COMPRESSED)), CompressedImage, on_compressed
        )
        assert wait_for(lambda: out_sub.get_num_connections() > 0)
        good, rgb = _image(rospy)
        # Until the node's publisher sees this subscriber too, frames are skipped as unwatched.
        assert wait_for(lambda: raw_pub.publish(good) or got.is_set(), 10.0), ros.output("image_compressor")[-1500:]
        out = received[0]
        assert out.header.stamp == good.header.stamp and out.header.frame_id == good.header.frame_id
        assert out.format == "rgb8; jpeg compressed bgr8"
        assert psnr_db(rgb, decode_jpeg(out.data)) > 30.0
        assert len(out.data) < len(good.data) / 8
        bad, _ = _image(rospy, encoding="rgba8")
        raw_pub.publish(bad)
        assert wait_for(
            lambda: (
                _reported(diagnostics, "/ic1/camera/image_compressor").get("invalid_messages") == "1"
                and _reported(diagnostics, "/ic1/camera/image_compressor").get("processed") == str(len(received))
            )
        )
        assert wait_for(lambda: "rgba8" in ros.output("image_compressor"))
    finally:
        for handle in (diag_sub, raw_pub, out_sub):
            if handle is not None:
                handle.unregister()


def test_rate_cap_and_remapped_output(ros, rospy_node):
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import CompressedImage, Image

    ros.start_node(
        "cps_transport",
        "image_compressor",
        name="capped_compressor",
        namespace="/ic2",
        params={"~max_rate_hz": 2.0},
        remap={"~input": "/ic2/image_raw", "~output": "/ic2/video"},
    )
    ros.wait_for_topic("/ic2/video", timeout_s=20)
    received, diagnostics = [], []
    out_sub = rospy.Subscriber("/ic2/video", CompressedImage, received.append)
    diag_sub = rospy.Subscriber(names.DIAGNOSTICS, DiagnosticArray, diagnostics.append)
    raw_pub = rospy.Publisher("/ic2/image_raw", Image, queue_size=10)
    try:
        assert wait_for(lambda: raw_pub.get_num_connections() > 0 and out_sub.get_num_connections() > 0)
        msg, _ = _image(rospy, width=64, height=48)
        start, sent = time.monotonic(), 0
        while sent < 30 or (not received and time.monotonic() - start < 10.0):  # 20 Hz, >= 1.5 s
            raw_pub.publish(msg)
            sent += 1
            time.sleep(0.05)
        elapsed_s = time.monotonic() - start
        end = rospy.Time.now() + rospy.Duration(1.0)

        def final_counts_delivered():
            """A report made after the node handled the last frame, and every frame it encoded received."""
            last = [a for a in diagnostics if a.status and a.status[0].name == "/ic2/capped_compressor"]
            return (
                bool(last)
                and last[-1].header.stamp > end
                and int(_reported(diagnostics, "/ic2/capped_compressor").get("processed", -1)) == len(received)
            )

        assert wait_for(final_counts_delivered, 10.0), (_reported(diagnostics, "/ic2/capped_compressor"), sent)
        # 2 Hz with a credit of one frame at the start, one more for scheduling slack.
        assert 2 <= len(received) <= 2 + 2.0 * elapsed_s, (len(received), elapsed_s)
    finally:
        for handle in (out_sub, diag_sub, raw_pub):
            handle.unregister()


@pytest.mark.parametrize(
    "params,name",
    [
        ({"~jpeg_quality": 0}, "~jpeg_quality"),
        ({"~jpeg_quality": 101}, "~jpeg_quality"),
        ({"~max_rate_hz": -1.0}, "~max_rate_hz"),
    ],
)
def test_bad_parameters_stop_the_node_naming_them(ros, params, name):
    node = f"bad_compressor_{abs(hash(name)) % 1000}_{list(params.values())[0]}".replace(".", "_").replace("-", "m")
    proc = ros.start_node("cps_transport", "image_compressor", name=node, namespace="/ic3", params=params)
    proc.wait(30)
    assert proc.returncode != 0
    assert name.lstrip("~") in ros.output(node)
