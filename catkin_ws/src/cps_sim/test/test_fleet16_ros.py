"""The simulator takes a generated fleet: fleet_sim with the 16-robot fleet file (light profile)
starts, and every robot publishes odometry and its sensor's clouds."""

import os
import time

import pytest

from cps_fleet import names
from cps_fleet.fleet import default_fleet_path, load_fleet
from cps_harness.testing import TopicRecorder

pytestmark = pytest.mark.ros

FLEET16 = os.path.join(os.path.dirname(default_fleet_path()), "fleets", "fleet16.yaml")


def test_fleet_sim_runs_the_sixteen_robot_fleet(ros, rospy_node):
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import PointCloud2

    fleet = load_fleet(FLEET16, profile="light")
    odom = {
        r.name: TopicRecorder(names.absolute(names.robot_topic(r.name, names.ODOM)), Odometry) for r in fleet.robots
    }
    clouds = {
        r.name: TopicRecorder(names.absolute(names.robot_topic(r.name, r.cloud_topic)), PointCloud2)
        for r in fleet.robots
    }
    try:
        # Its own name: private parameters outlive the node on the session's master, and a later
        # test's `fleet_sim` would read this one's ~fleet_file.
        ros.start_node(
            "cps_sim", "fleet_sim", name="fleet_sim_fleet16", params={"~fleet_file": FLEET16, "~profile": "light"}
        )
        deadline = time.monotonic() + 50.0
        for robot in fleet.robots:
            first = odom[robot.name].wait(timeout_s=max(deadline - time.monotonic(), 1.0))
            assert first.header.frame_id == names.odom_frame(robot.name)
            cloud = clouds[robot.name].wait(timeout_s=max(deadline - time.monotonic(), 1.0))
            assert cloud.header.frame_id == robot.sensor_frame and cloud.width * cloud.height > 0, robot.name
    finally:
        for recorder in list(odom.values()) + list(clouds.values()):
            recorder.close()
