"""The encoder and decoder nodes carry a cloud from /<r>/points_filtered to /twin/<r>/points with
its stamp and frame; bad messages are dropped, counted (also in /tissue/stats) and nothing else is lost."""

import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.synthetic_clouds import depth_camera_cloud
from cps_harness.testing import wait_for
from cps_transport.draco import DracoEncoder
from cps_transport.pointcloud import array_to_cloud, cloud_to_array, xyz_of
from cps_transport.voxel import voxel_downsample

pytestmark = pytest.mark.ros


def _collect(rospy, topic, msg_type):
    received, event = [], threading.Event()

    def on_msg(msg):
        received.append(msg)
        event.set()

    return rospy.Subscriber(topic, msg_type, on_msg), received, event


R = "tn1"


@pytest.fixture
def pipeline(ros, rospy_node):
    """Encoder in /tn1, decoder on the twin, topic_stats on the compressed topic; a voxel-filtered cloud."""
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import CompressedPointCloud2, TopicStatsArray

    ros.start_node(
        "cps_transport",
        "draco_encoder",
        name="draco_encoder",
        namespace=names.absolute(R),
        params={"~leaf_size_m": 0.1, "~fields": "xyz,rgb"},
        remap={"~input": names.absolute(names.robot_topic(R, names.POINTS_FILTERED))},
    )
    ros.start_node(
        "cps_transport",
        "draco_decoder",
        name="draco_decoder",
        namespace=names.absolute(names.TWIN_NS),
        remap={
            "~input": names.absolute(names.robot_topic(R, names.POINTS_DRACO)),
            "~output": names.absolute(names.twin_points(R)),
        },
    )
    ros.start_node(
        "cps_transport",
        "topic_stats",
        name="topic_stats",
        namespace=names.absolute(R),
        params={"~topics": [names.absolute(names.robot_topic(R, names.POINTS_DRACO))], "~publish_rate_hz": 4.0},
    )
    ros.wait_for_topic(names.absolute(names.robot_topic(R, names.POINTS_DRACO)), timeout_s=20)
    ros.wait_for_topic(names.absolute(names.twin_points(R)), timeout_s=20)

    p = SimpleNamespace(rospy=rospy)
    out_sub, p.decoded, p.got = _collect(rospy, names.absolute(names.twin_points(R)), PointCloud2)
    stats_sub, p.stats, _ = _collect(
        rospy, names.absolute(names.TISSUE_STATS, names.absolute(R)), TopicStatsArray
    )  # relative, in its namespace
    diag_sub, p.diagnostics, _ = _collect(rospy, names.DIAGNOSTICS, DiagnosticArray)
    p.raw_pub = rospy.Publisher(names.absolute(names.robot_topic(R, names.POINTS_FILTERED)), PointCloud2, queue_size=10)
    p.compressed_pub = rospy.Publisher(
        names.absolute(names.robot_topic(R, names.POINTS_DRACO)), CompressedPointCloud2, queue_size=10
    )

    points = cloud_to_array(depth_camera_cloud(width=160, height=120))
    p.centroids, extras = voxel_downsample(xyz_of(points), 0.1, {"rgb": points["rgb"]})
    p.filtered = array_to_cloud({"x": p.centroids[:, 0], "y": p.centroids[:, 1], "z": p.centroids[:, 2], **extras})
    p.filtered.header.frame_id = f"{R}/camera_depth_optical_frame"
    try:
        # The encoder reads the raw topic; the decoder and topic_stats both read the compressed one.
        assert wait_for(lambda: p.raw_pub.get_num_connections() >= 1 and p.compressed_pub.get_num_connections() >= 2)
        yield p
    finally:
        for handle in (out_sub, stats_sub, diag_sub, p.raw_pub, p.compressed_pub):
            handle.unregister()


def _reported_invalid(diagnostics, node):
    for array in reversed(diagnostics):
        for status in array.status:
            if status.name == node:
                return int({kv.key: kv.value for kv in status.values}["invalid_messages"])
    return None


def test_encoder_drops_bad_clouds_and_the_next_crosses_with_stamp_and_frame(ros, pipeline):
    from sensor_msgs.msg import PointCloud2

    p, c = pipeline, pipeline.centroids
    short = array_to_cloud({"x": c[:5, 0], "y": c[:5, 1], "z": c[:5, 2]})
    short.data = short.data[:-3]
    no_z = array_to_cloud({"x": c[:5, 0], "y": c[:5, 1], "w": c[:5, 2]})
    empty = PointCloud2(fields=p.filtered.fields, point_step=p.filtered.point_step, height=1, width=0)
    for bad in (short, no_z, empty):
        p.raw_pub.publish(bad)
        time.sleep(0.05)
    p.filtered.header.stamp = p.rospy.Time.now()
    p.raw_pub.publish(p.filtered)
    assert p.got.wait(15.0), "nothing came out of the decoder"
    out = p.decoded[0]
    assert out.header.stamp == p.filtered.header.stamp and out.header.frame_id == p.filtered.header.frame_id
    assert out.height == 1 and [f.name for f in out.fields] == ["x", "y", "z", "rgb"]
    np.testing.assert_allclose(xyz_of(cloud_to_array(out)), c, atol=0.05)
    assert wait_for(lambda: _reported_invalid(p.diagnostics, f"/{R}/draco_encoder") == 3), (
        _reported_invalid(p.diagnostics, f"/{R}/draco_encoder"),
        ros.output("draco_encoder")[-1500:],
    )
    assert all(proc.poll() is None for proc in ros.processes)


def test_decoder_drops_bad_payloads_counts_them_in_the_stats_and_decodes_the_next(ros, pipeline):
    p = pipeline
    good = DracoEncoder(leaf_size_m=0.1).encode(p.filtered)
    truncated = DracoEncoder(leaf_size_m=0.1).encode(p.filtered)
    truncated.compressed_data = bytes(good.compressed_data)[: len(good.compressed_data) // 3]
    corrupt = DracoEncoder(leaf_size_m=0.1).encode(p.filtered)
    corrupt.compressed_data = bytes(255 - b for b in bytes(good.compressed_data))
    unknown_type = DracoEncoder(leaf_size_m=0.1).encode(p.filtered)
    unknown_type.fields[0].datatype = 99
    for bad in (truncated, corrupt, unknown_type):
        p.compressed_pub.publish(bad)
        time.sleep(0.05)
    good.header.stamp = p.rospy.Time.now()
    p.compressed_pub.publish(good)
    assert wait_for(lambda: any(m.header.stamp == good.header.stamp for m in p.decoded), 15.0)
    assert wait_for(lambda: _reported_invalid(p.diagnostics, names.absolute(names.in_twin("draco_decoder"))) == 3), (
        _reported_invalid(p.diagnostics, names.absolute(names.in_twin("draco_decoder"))),
        ros.output("draco_decoder")[-1500:],
    )

    def invalid_in_stats():
        for array in reversed(p.stats):
            for item in array.topics:
                if item.topic == names.absolute(names.robot_topic(R, names.POINTS_DRACO)):
                    return item.invalid_messages
        return None

    assert wait_for(lambda: invalid_in_stats() == 3)
    assert "dropped a message" in ros.output("draco_decoder")
    assert all(proc.poll() is None for proc in ros.processes)


def test_encoder_refuses_a_bad_parameter(ros):
    proc = ros.start_node(
        "cps_transport",
        "draco_encoder",
        name="bad_encoder",
        namespace="/tn2",
        params={"~speed": 11, "~leaf_size_m": 0.1},
    )
    proc.wait(30)
    assert proc.returncode != 0
    assert "~speed" in ros.output("bad_encoder") or "speed" in ros.output("bad_encoder")
