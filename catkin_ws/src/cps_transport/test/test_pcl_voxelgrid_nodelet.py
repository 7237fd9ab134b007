"""pcl_ros's pcl/VoxelGrid nodelet loads from Debian's packages (with ci/setup.sh's plugin-path
fix) and filters a cloud, including points beyond 1 m when filter_field_name is empty."""

import threading

import numpy as np
import pytest

from cps_fleet import names

pytestmark = pytest.mark.ros


def _cloud(points, frame="cloud_frame"):
    import rospy
    from sensor_msgs.msg import PointCloud2, PointField

    msg = PointCloud2()
    msg.header.stamp = rospy.Time.now()
    msg.header.frame_id = frame
    msg.height, msg.width = 1, len(points)
    msg.fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1) for i, n in enumerate("xyz")]
    msg.is_bigendian = False
    msg.point_step, msg.row_step = 12, 12 * len(points)
    msg.is_dense = True
    msg.data = np.asarray(points, dtype=np.float32).tobytes()
    return msg


def _xyz(msg):
    offsets = {f.name: f.offset for f in msg.fields}
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(-1, msg.point_step)
    return np.stack([raw[:, offsets[a] : offsets[a] + 4].copy().view("<f4")[:, 0] for a in "xyz"], axis=1)


def test_voxelgrid_nodelet_loads_and_filters(ros, rospy_node):
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2

    ros.popen(
        [
            "rosrun",
            "nodelet",
            "nodelet",
            "standalone",
            "pcl/VoxelGrid",
            "__name:=voxel_test",
            "~input:=/voxel_test/in",
            "~output:=/voxel_test/out",
            "_leaf_size:=0.5",
            "_filter_field_name:=",
            "_filter_limit_min:=-1000",
            "_filter_limit_max:=1000",
        ],
        name="voxel_nodelet",
    )
    ros.wait_for_topic("/voxel_test/out", timeout_s=30)

    received = []
    got = threading.Event()

    def on_cloud(msg):
        received.append(msg)
        got.set()

    sub = rospy.Subscriber("/voxel_test/out", PointCloud2, on_cloud)
    pub = rospy.Publisher("/voxel_test/in", PointCloud2, queue_size=1, latch=True)
    # Two clusters of points: one near, one 10 m away (beyond pcl's default 0..1 m z filter).
    rng = np.random.default_rng(0)
    near = rng.uniform(0.01, 0.24, size=(200, 3))
    far = rng.uniform(0.01, 0.24, size=(200, 3)) + [0.0, 0.0, 10.0]
    try:
        for _ in range(100):
            pub.publish(_cloud(np.vstack([near, far])))
            if got.wait(0.3):
                break
        assert received, "no filtered cloud came out of pcl/VoxelGrid:\n" + ros.output("voxel_nodelet")[-2000:]
        out = _xyz(received[-1])
        assert len(out) == 2, f"expected one centroid per occupied voxel, got {len(out)}"
        centroids = sorted(out.tolist(), key=lambda p: p[2])
        assert np.allclose(centroids[0], near.mean(axis=0), atol=1e-4)
        assert np.allclose(centroids[1], far.mean(axis=0), atol=1e-4)
    finally:
        sub.unregister()
        pub.unregister()


def test_voxel_nodelet_args_match_numpy_voxel_downsample(ros, rospy_node):
    """The bringup's command line (leaf from fleet.yaml, no field filter) gives the same centroids
    as cps_transport.voxel.voxel_downsample on an organized depth cloud with NaNs, 15 m deep."""
    import dataclasses

    from sensor_msgs.msg import PointCloud2

    from cps_fleet.fleet import load_fleet
    from cps_harness.synthetic_clouds import depth_camera_cloud
    from cps_transport import voxel_nodelet_args
    from cps_transport.pointcloud import cloud_to_array, xyz_of
    from cps_transport.voxel import voxel_downsample

    rospy = rospy_node
    robot = dataclasses.replace(load_fleet().robot("jackal"), name="vgtest")
    ros.popen(voxel_nodelet_args(robot), name="voxel_args")
    ros.wait_for_topic(names.absolute(names.robot_topic("vgtest", names.POINTS_FILTERED)), timeout_s=30)
    received, got = [], threading.Event()
    sub = rospy.Subscriber(
        names.absolute(names.robot_topic("vgtest", names.POINTS_FILTERED)),
        PointCloud2,
        lambda m: (received.append(m), got.set()),
    )
    pub = rospy.Publisher(
        names.absolute(names.robot_topic("vgtest", names.POINTS)), PointCloud2, queue_size=1, latch=True
    )
    cloud = depth_camera_cloud(width=320, height=240)
    try:
        for _ in range(100):
            cloud.header.stamp = rospy.Time.now()
            pub.publish(cloud)
            if got.wait(0.3):
                break
        assert received, "no output from the nodelet:\n" + ros.output("voxel_args")[-2000:]
        theirs = xyz_of(cloud_to_array(received[-1]))
        ours = voxel_downsample(xyz_of(cloud_to_array(cloud)), robot.voxel_leaf_m)
        assert theirs[:, 2].max() > 10.0, "points beyond 1 m were dropped"
        assert len(theirs) == len(ours)
        np.testing.assert_allclose(theirs, ours, atol=1e-4)
    finally:
        sub.unregister()
        pub.unregister()
