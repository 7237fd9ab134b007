"""Fixtures of cps_link's tests (the workspace's ros_master/ros/rospy_node come from the top conftest)."""

import sys

import pytest

from cps_fleet import names
from cps_ros.processes import RosGraph, find_node

CLOUD_LOAD = find_node("cps_harness", "cloud_load")
# map -> load (the frame of cloud_load.py's clouds), latched on /tf_static: the robots' bridge needs
# it for the keyframes' poses.
STATIC_TF = [
    sys.executable,
    "-c",
    "import rospy, tf2_ros; from geometry_msgs.msg import TransformStamped; "
    "rospy.init_node('static_tf'); t = TransformStamped(); t.header.frame_id = 'map'; "
    "t.child_frame_id = 'load'; t.transform.translation.x, t.transform.translation.y, "
    "t.transform.translation.z = 1, 2, 3; t.transform.rotation.w = 1; "
    "b = tf2_ros.StaticTransformBroadcaster(); b.sendTransform(t); rospy.spin()",
]


@pytest.fixture
def robots_graph():
    """A second, private master: the robots' side, while the session's master is the twin's."""
    graph = RosGraph()
    graph.start()
    try:
        yield graph
    finally:
        graph.close()


@pytest.fixture
def managed_cloud_load(rospy_node, robots_graph, request):
    """Returns start(robot): 20 kB clouds at 5 Hz on the robot's managed topic on the robots' side,
    the map -> load transform, and, as the manager would, an allocation at 2 Hz leaving 0.5 MB/s
    of a 6 MB/s budget unused (what paces the backfill)."""
    from cps_msgs.msg import BandwidthAllocationArray

    def start(robot):
        robots_graph.popen(STATIC_TF, name="static_tf")
        robots_graph.popen(
            [
                sys.executable,
                CLOUD_LOAD,
                f"{robot}:20000:5",
                f"{names.absolute(names.robot_topic(robot, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(robot))}",
            ],
            name="load",
        )
        allocation = rospy_node.Publisher(names.absolute(names.ALLOCATION), BandwidthAllocationArray, queue_size=1)
        timer = rospy_node.Timer(
            rospy_node.Duration(0.5),
            lambda _e: allocation.publish(
                BandwidthAllocationArray(budget_mbytes_per_s=6.0, allocated_mbytes_per_s=5.5)
            ),
        )
        request.addfinalizer(allocation.unregister)
        request.addfinalizer(timer.shutdown)

    return start
