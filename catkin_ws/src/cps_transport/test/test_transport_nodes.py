"""The encoder and decoder nodes carry a cloud from /<r>/points_filtered to /twin/<r>/points with
its stamp and frame; bad messages are dropped, counted (also in /tissue/stats) and nothing else is lost."""
import threading
import time

import numpy as np
import pytest

from cps_harness.testing import wait_for
from cps_transport.draco import DracoEncoder
from cps_transport.pointcloud import array_to_cloud, cloud_to_array, xyz_of
from cps_harness.synthetic_clouds import depth_camera_cloud
from cps_transport.voxel import voxel_downsample

pytestmark = pytest.mark.ros


def _collect(rospy, topic, msg_type):
    received, event = [], threading.Event()

    def on_msg(msg):
        received.append(msg)
        event.set()
    return rospy.Subscriber(topic, msg_type, on_msg), received, event



def test_encoder_decoder_nodes_round_trip_and_survive_bad_input(ros, rospy_node):
    rospy = rospy_node
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import CompressedPointCloud2, TopicStatsArray

    r = "tn1"
    ros.start_node("cps_transport", "draco_encoder", name="draco_encoder", namespace=f"/{r}",
                   params={"~leaf_size_m": 0.1, "~fields": "xyz,rgb"}, remap={"~input": f"/{r}/points_filtered"})
    ros.start_node("cps_transport", "draco_decoder", name="draco_decoder", namespace="/twin",
                   remap={"~input": f"/{r}/points_filtered/draco", "~output": f"/twin/{r}/points"})
    ros.start_node("cps_transport", "topic_stats", name="topic_stats", namespace=f"/{r}",
                   params={"~topics": [f"/{r}/points_filtered/draco"], "~publish_rate_hz": 4.0})
    ros.wait_for_topic(f"/{r}/points_filtered/draco", timeout_s=20)
    ros.wait_for_topic(f"/twin/{r}/points", timeout_s=20)

    out_sub, decoded, got = _collect(rospy, f"/twin/{r}/points", PointCloud2)
    stats_sub, stats, _ = _collect(rospy, "/tissue/stats", TopicStatsArray)
    diag_sub, diagnostics, _ = _collect(rospy, "/diagnostics", DiagnosticArray)
    raw_pub = rospy.Publisher(f"/{r}/points_filtered", PointCloud2, queue_size=10)
    compressed_pub = rospy.Publisher(f"/{r}/points_filtered/draco", CompressedPointCloud2, queue_size=10)

    depth = depth_camera_cloud(width=160, height=120)
    points = cloud_to_array(depth)
    centroids, extras = voxel_downsample(xyz_of(points), 0.1, {"rgb": points["rgb"]})
    filtered = array_to_cloud({"x": centroids[:, 0], "y": centroids[:, 1], "z": centroids[:, 2], **extras})
    filtered.header.frame_id = f"{r}/camera_depth_optical_frame"
    try:
        wait_for(lambda: raw_pub.get_num_connections() > 0 and compressed_pub.get_num_connections() > 0)
        # Bad raw clouds for the encoder, then a good one.
        short = array_to_cloud({"x": centroids[:5, 0], "y": centroids[:5, 1], "z": centroids[:5, 2]})
        short.data = short.data[:-3]
        no_z = array_to_cloud({"x": centroids[:5, 0], "y": centroids[:5, 1], "w": centroids[:5, 2]})
        empty = PointCloud2(fields=filtered.fields, point_step=filtered.point_step, height=1, width=0)
        for bad in (short, no_z, empty):
            raw_pub.publish(bad)
            time.sleep(0.05)
        filtered.header.stamp = rospy.Time.now()
        raw_pub.publish(filtered)
        assert got.wait(15.0), "nothing came out of the decoder"
        out = decoded[0]
        assert out.header.stamp == filtered.header.stamp and out.header.frame_id == filtered.header.frame_id
        assert out.height == 1 and [f.name for f in out.fields] == ["x", "y", "z", "rgb"]
        np.testing.assert_allclose(xyz_of(cloud_to_array(out)), centroids, atol=0.05)

        # Bad compressed clouds for the decoder, then a good one.
        good = DracoEncoder(leaf_size_m=0.1).encode(filtered)
        truncated = DracoEncoder(leaf_size_m=0.1).encode(filtered)
        truncated.compressed_data = bytes(good.compressed_data)[:len(good.compressed_data) // 3]
        corrupt = DracoEncoder(leaf_size_m=0.1).encode(filtered)
        corrupt.compressed_data = bytes(255 - b for b in bytes(good.compressed_data))
        unknown_type = DracoEncoder(leaf_size_m=0.1).encode(filtered)
        unknown_type.fields[0].datatype = 99
        got.clear()
        for bad in (truncated, corrupt, unknown_type):
            compressed_pub.publish(bad)
            time.sleep(0.05)
        good.header.stamp = rospy.Time.now()
        compressed_pub.publish(good)
        assert wait_for(lambda: any(m.header.stamp == good.header.stamp for m in decoded), 15.0)

        def reported(node):
            for array in reversed(diagnostics):
                for status in array.status:
                    if status.name == node:
                        return int({kv.key: kv.value for kv in status.values}["invalid_messages"])
            return None
        assert wait_for(lambda: reported(f"/{r}/draco_encoder") == 3 and reported("/twin/draco_decoder") == 3), (
            reported(f"/{r}/draco_encoder"), reported("/twin/draco_decoder"), ros.output("draco_encoder")[-1500:])

        def invalid_in_stats():
            for array in reversed(stats):
                for item in array.topics:
                    if item.topic == f"/{r}/points_filtered/draco":
                        return item.invalid_messages
            return None
        assert wait_for(lambda: invalid_in_stats() == 3)
        assert "dropped a message" in ros.output("draco_decoder")
        assert all(proc.poll() is None for proc in ros.processes)
    finally:
        for handle in (out_sub, stats_sub, diag_sub, raw_pub, compressed_pub):
            handle.unregister()


def test_encoder_refuses_a_bad_parameter(ros):
    proc = ros.start_node("cps_transport", "draco_encoder", name="bad_encoder", namespace="/tn2",
                          params={"~speed": 11, "~leaf_size_m": 0.1})
    proc.wait(30)
    assert proc.returncode != 0
    assert "~speed" in ros.output("bad_encoder") or "speed" in ros.output("bad_encoder")
