"""The robot's tissue follows the manager's cloud level: publishing /<r>/cloud_throttle/level makes
pcl_ros's VoxelGrid filter at that level's leaf, every managed cloud carries that leaf, and the
rate limiter's status reports the level and its own mean size (private master, real nodes)."""

import math

import pytest

from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_harness.testing import TopicRecorder, wait_for
from cps_transport.cloud_levels import cloud_level_leaves, initial_leaf_m, level_of_leaf, one_point_per_voxel

pytestmark = pytest.mark.ros

ROBOT = "jackal"


def _xyz(cloud):
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    return xyz_of(cloud_to_array(cloud))


def _filtered_at(leaf, coarser):
    """A voxel grid's output at `leaf`: one point per voxel of it, several in some of `coarser`."""
    return lambda msg: (
        one_point_per_voxel(_xyz(msg), leaf) and (coarser is None or not one_point_per_voxel(_xyz(msg), coarser))
    )


def _start_shared(ros, fleet):
    """The shared layout: a nodelet manager with the loader's voxel grid, one cloud_tissue."""
    ros.popen(["rosrun", "nodelet", "nodelet", "manager", "__name:=level_manager"], name="level_manager")
    ros.start_node(
        "cps_transport",
        "voxel_grid_loader",
        name="voxel_grid_loader",
        params={"~robots": ROBOT, "~manager": "/level_manager"},
    )
    ros.start_node(
        "cps_transport", "cloud_tissue", name="cloud_tissue", params={"~robots": ROBOT, "~initial_rate_hz": 30.0}
    )
    return "cloud_tissue", "cloud_tissue", None


def _start_per_robot(ros, fleet):
    """The per_robot layout as the bringup starts it: a standalone voxel grid, draco_encoder and
    rate_limiter processes in the robot's namespace, both with ~cloud_levels."""
    from cps_transport.voxel_grid_command import voxel_nodelet_args

    robot = fleet.robot(ROBOT)
    argv = voxel_nodelet_args(robot, leaf_size_m=initial_leaf_m(fleet, robot))
    voxel_grid = [ros.popen(argv, name="voxel_grid")]

    def restart_voxel_grid():
        """The voxel grid dies and comes back at its initial leaf, as after a manager restart."""
        ros.stop(voxel_grid[0])
        voxel_grid[0] = ros.popen(argv, name="voxel_grid")

    ros.start_node(
        "cps_transport",
        "draco_encoder",
        name="draco_encoder",
        namespace=names.absolute(ROBOT),
        params={"~cloud_levels": True},
        remap={
            "~input": names.absolute(names.robot_topic(ROBOT, names.POINTS_FILTERED)),
            "~output": names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO)),
        },
    )
    ros.start_node(
        "cps_transport",
        "rate_limiter",
        name=names.CLOUD_THROTTLE,
        namespace=names.absolute(ROBOT),
        params={"~cloud_levels": True, "~rate_hz": 30.0},
        remap={
            "~input": names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO)),
            "~output": names.absolute(names.robot_topic(ROBOT, names.POINTS_MANAGED)),
        },
    )
    return "draco_encoder", names.CLOUD_THROTTLE, restart_voxel_grid


@pytest.mark.parametrize("start", [_start_shared, _start_per_robot], ids=["shared", "per_robot"])
def test_level_topic_changes_the_leaf_the_tissue_emits_and_the_status_level(ros, rospy_node, start):
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import UInt8

    from cps_harness.synthetic_clouds import depth_camera_cloud
    from cps_msgs.msg import CompressedPointCloud2, RateLimiterStatus
    from cps_transport.draco import leaf_of_compressed

    fleet = load_fleet()
    leaves = cloud_level_leaves(fleet)
    start_leaf = initial_leaf_m(fleet, fleet.robot(ROBOT))
    follower, limiter, restart_voxel_grid = start(ros, fleet)
    managed = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.POINTS_MANAGED)), CompressedPointCloud2)
    filtered = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.POINTS_FILTERED)), PointCloud2)
    status = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.LIMITER_STATUS)), RateLimiterStatus)
    level_pub = rospy.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.LIMITER_LEVEL)), UInt8, queue_size=1, latch=True
    )
    cloud_pub = rospy.Publisher(
        names.absolute(names.robot_topic(ROBOT, fleet.robot(ROBOT).cloud_topic)), PointCloud2, queue_size=2
    )
    cloud = depth_camera_cloud(width=320, height=240, far_m=8.0)

    def feed_until(predicate, timeout_s=60.0):
        """Publish the camera cloud until the newest managed cloud satisfies `predicate`."""

        def check():
            cloud.header.stamp = rospy.Time.now()
            cloud_pub.publish(cloud)
            latest = managed.latest
            return latest is not None and predicate(latest)

        return wait_for(check, timeout_s=timeout_s, poll_s=0.1)

    def leaf_is(leaf):
        return lambda msg: abs(leaf_of_compressed(msg) - leaf) < 1e-6

    try:
        ros.wait_for_topic(names.absolute(names.robot_topic(ROBOT, names.POINTS_FILTERED)), timeout_s=60)
        assert feed_until(leaf_is(start_leaf)), ros.output(follower)[-3000:] + ros.output(limiter)[-2000:]
        for level in (2, 0):
            level_pub.publish(UInt8(data=level))
            assert feed_until(leaf_is(leaves[level])), (
                f"no cloud at level {level}: " + ros.output(follower)[-3000:] + ros.output(limiter)[-2000:]
            )
            assert level_of_leaf(leaves, leaf_of_compressed(managed.latest)) == level
            # the voxel grid really filters at that leaf now (its own output; Draco then moves
            # points by up to cloud_levels.position_tolerance_m)
            coarser = leaves[level + 1] if level + 1 < len(leaves) else None
            filtered.wait(_filtered_at(leaves[level], coarser), timeout_s=20, what=f"a cloud at {leaves[level]} m")
            last = status.wait(
                lambda s, level=level: s.level == level and math.isfinite(s.level_mean_message_bytes),
                timeout_s=20,
                what=f"status at level {level}",
            )
            assert 0 < last.level_mean_message_bytes
        sizes, points = {}, {}
        # The status' level mean is the size at that level only: the fine level's is larger.
        for level in (2, 0):
            level_pub.publish(UInt8(data=level))
            assert feed_until(leaf_is(leaves[level]))
            report = status.wait(
                lambda s, level=level: s.level == level and math.isfinite(s.level_mean_message_bytes),
                timeout_s=20,
            )
            sizes[level], points[level] = report.level_mean_message_bytes, report.level_mean_points
            # issue 36: where the limiter runs, and (the shared tissue, whose encoder is in the
            # limiter's process) what the level costs the robots' side
            assert report.host and report.host_cpus >= 1, report
            assert math.isnan(report.host_idle_fraction) or 0 <= report.host_idle_fraction <= 1
            if start is _start_shared:
                assert report.level_mean_cpu_s > 0 and report.level_mean_points > 0, report
        # (this 320 x 240 view: 0.05 m clouds are 2.8-3.5x the 0.2 m ones, measured; 2x is the bound)
        # on failure, the statuses as they came (level: level mean / mean) and the follower's log
        assert sizes[0] > 2 * sizes[2], (
            sizes,
            [
                f"{m.level}:{m.level_mean_message_bytes:.0f}/{m.mean_message_bytes:.0f}"
                for _, m in status.messages[-40:]
            ],
            ros.output(follower)[-2000:],
        )
        if start is _start_shared:
            assert points[0] > 2 * points[2], points
        if restart_voxel_grid is not None:
            # level 0 (0.05 m) in force; a voxel grid back at its initial 0.10 m is set to 0.05 m again
            restart_voxel_grid()
            assert wait_for(lambda: "restarted): setting it" in ros.output(follower), timeout_s=60), ros.output(
                follower
            )[-2000:]
            filtered.take()  # only clouds the new voxel grid filtered count now

            def refiltered():
                cloud.header.stamp = rospy.Time.now()
                cloud_pub.publish(cloud)
                latest = filtered.latest
                return latest is not None and _filtered_at(leaves[0], leaves[1])(latest)

            assert wait_for(refiltered, timeout_s=60, poll_s=0.1), "no 0.05 m cloud from the restarted voxel grid"
            assert feed_until(leaf_is(leaves[0]))
        # A level past the fleet's levels is refused and counted; the leaf stays.
        level_pub.publish(UInt8(data=len(leaves) + 4))
        assert wait_for(lambda: "is not one of the 3 cloud levels" in ros.output(follower), timeout_s=20), ros.output(
            follower
        )[-2000:]
        assert feed_until(leaf_is(leaves[0]))
    finally:
        managed.close()
        filtered.close()
        status.close()
        level_pub.unregister()
        cloud_pub.unregister()


def test_a_level_published_before_the_voxel_grid_is_up_is_set_when_it_comes(ros, rospy_node):
    """The manager's latched level reaches the encoder before the voxel grid offers its service
    (the set fails, counted); once the voxel grid is up at its initial leaf, it is set to the level."""
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import UInt8

    from cps_harness.synthetic_clouds import depth_camera_cloud
    from cps_msgs.msg import CompressedPointCloud2
    from cps_transport.draco import leaf_of_compressed
    from cps_transport.voxel_grid_command import voxel_nodelet_args

    fleet = load_fleet()
    leaves = cloud_level_leaves(fleet)
    robot = fleet.robot(ROBOT)
    level_pub = rospy.Publisher(
        names.absolute(names.robot_topic(ROBOT, names.LIMITER_LEVEL)), UInt8, queue_size=1, latch=True
    )
    level_pub.publish(UInt8(data=2))
    ros.start_node(
        "cps_transport",
        "draco_encoder",
        name="draco_encoder",
        namespace=names.absolute(ROBOT),
        params={"~cloud_levels": True},
        remap={
            "~input": names.absolute(names.robot_topic(ROBOT, names.POINTS_FILTERED)),
            "~output": names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO)),
        },
    )
    draco = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO)), CompressedPointCloud2)
    filtered = TopicRecorder(names.absolute(names.robot_topic(ROBOT, names.POINTS_FILTERED)), PointCloud2)
    cloud_pub = rospy.Publisher(names.absolute(names.robot_topic(ROBOT, robot.cloud_topic)), PointCloud2, queue_size=2)
    cloud = depth_camera_cloud(width=320, height=240, far_m=8.0)
    try:
        assert wait_for(lambda: "did not take leaf 0.2 m" in ros.output("draco_encoder"), timeout_s=60), ros.output(
            "draco_encoder"
        )[-2000:]
        ros.popen(voxel_nodelet_args(robot, leaf_size_m=initial_leaf_m(fleet, robot)), name="voxel_grid")

        def at_level_2():
            cloud.header.stamp = rospy.Time.now()
            cloud_pub.publish(cloud)
            latest, raw = draco.latest, filtered.latest
            return (
                latest is not None
                and abs(leaf_of_compressed(latest) - leaves[2]) < 1e-6
                and raw is not None
                and _filtered_at(leaves[2], None)(raw)
                and not one_point_per_voxel(_xyz(raw), 2 * leaves[2])
            )

        assert wait_for(at_level_2, timeout_s=60, poll_s=0.1), ros.output("draco_encoder")[-2000:]
        assert "started late or restarted): setting it" in ros.output("draco_encoder")
    finally:
        draco.close()
        filtered.close()
        level_pub.unregister()
        cloud_pub.unregister()
