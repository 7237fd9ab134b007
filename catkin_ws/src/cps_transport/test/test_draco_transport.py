"""DracoPublisher/DracoSubscriber: a cloud published on a base topic travels as `<base>/draco` and
reaches the user's callback decoded; a corrupt payload and an unencodable cloud are counted and
the next good cloud still arrives."""

import threading

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.synthetic_clouds import depth_camera_cloud
from cps_harness.testing import wait_for
from cps_transport.pointcloud import array_to_cloud, cloud_to_array, xyz_of
from cps_transport.voxel import voxel_downsample

pytestmark = pytest.mark.ros


def test_round_trip_and_corrupt_payload_counted(ros, rospy_node):
    rospy = rospy_node
    from cps_msgs.msg import CompressedPointCloud2
    from cps_transport.draco_transport import DracoPublisher, DracoSubscriber

    base = names.absolute(names.robot_topic("dtp1", names.POINTS_FILTERED))
    received, got = [], threading.Event()

    def on_cloud(cloud):
        received.append(cloud)
        got.set()

    publisher = DracoPublisher(base, leaf_size_m=0.1, fields="xyz,rgb")
    subscriber = DracoSubscriber(base, on_cloud)
    assert publisher.topic == subscriber.topic == base + "/draco"
    intruder = rospy.Publisher(base + "/draco", CompressedPointCloud2, queue_size=10)

    depth = depth_camera_cloud(width=160, height=120)
    points = cloud_to_array(depth)
    centroids, extras = voxel_downsample(xyz_of(points), 0.1, {"rgb": points["rgb"]})
    cloud = array_to_cloud({"x": centroids[:, 0], "y": centroids[:, 1], "z": centroids[:, 2], **extras})
    cloud.header.frame_id = "dtp1/camera_depth_optical_frame"
    try:
        assert wait_for(
            lambda: (
                publisher.get_num_connections() > 0
                and intruder.get_num_connections() > 0
                and subscriber.get_num_connections() > 0
            )
        )
        cloud.header.stamp = rospy.Time.now()
        compressed = publisher.publish(cloud)
        assert compressed is not None and len(compressed.compressed_data) < len(cloud.data)
        assert got.wait(10.0), "the decoded cloud never reached the callback"
        out = received[0]
        assert out.header.stamp == cloud.header.stamp and out.header.frame_id == cloud.header.frame_id
        assert [f.name for f in out.fields] == ["x", "y", "z", "rgb"]
        np.testing.assert_allclose(xyz_of(cloud_to_array(out)), centroids, atol=0.05)
        np.testing.assert_array_equal(cloud_to_array(out)["rgb"], extras["rgb"])

        # An unencodable cloud is dropped at the publisher, counted, and nothing is sent.
        short = array_to_cloud({"x": centroids[:5, 0], "y": centroids[:5, 1], "z": centroids[:5, 2]})
        short.data = short.data[:-3]
        assert publisher.publish(short) is None and publisher.invalid == 1

        # A corrupt payload is dropped at the subscriber; the next good cloud arrives.
        corrupt = CompressedPointCloud2()
        corrupt.header, corrupt.height, corrupt.width = compressed.header, compressed.height, compressed.width
        corrupt.fields = compressed.fields
        corrupt.compressed_data = bytes(reversed(compressed.compressed_data))
        got.clear()
        intruder.publish(corrupt)
        assert wait_for(lambda: subscriber.invalid == 1), "the corrupt payload was not counted"
        assert len(received) == 1 and not got.is_set()
        cloud.header.stamp = rospy.Time.now()
        publisher.publish(cloud)
        assert got.wait(10.0), "the good cloud after the corrupt one never arrived"
        assert len(received) == 2 and received[1].header.stamp == cloud.header.stamp
        assert subscriber.invalid == 1 and subscriber.received == 2 and publisher.published == 2
    finally:
        publisher.unregister()
        subscriber.unregister()
        intruder.unregister()
