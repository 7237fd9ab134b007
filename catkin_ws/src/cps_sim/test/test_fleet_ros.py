"""The default fleet on a real master in the light profile: the contract's topics and frames,
and every route run to `done` through `inspecting` (each robot on the first ROUTE_WAYPOINTS
waypoints of its route, the second and third inspections: the whole routes took 80-95 s of the
suite and showed nothing more). One fleet for the whole module (starting it takes a minute)."""

import math
import time

import numpy as np
import pytest
from rostest_support import quat_yaw, start_robot_nodes

from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_harness.fleets import write_fleet_with_short_routes
from cps_harness.testing import TopicRecorder
from cps_sim.messages import cloud_to_array

pytestmark = pytest.mark.ros

ROBOTS = ("scout", "jackal", "champ", "iris")
# The default routes' first three waypoints: a transit, then two inspections (the state is
# `inspecting` on the way between them; 4-13 m of driving).
ROUTE_WAYPOINTS = 3
DEPTH_ROBOTS = ("jackal", "champ", "iris")


@pytest.fixture(scope="module")
def fleet_file(tmp_path_factory):
    return write_fleet_with_short_routes(str(tmp_path_factory.mktemp("fleet")), ROUTE_WAYPOINTS)


@pytest.fixture(scope="module")
def fleet(fleet_file):
    return load_fleet(fleet_file, profile="light")


@pytest.fixture(scope="module")
def running_fleet(ros_master, rospy_node, fleet_file):
    """fleet_sim (with sensor workers) and every robot's mux and route controller; the mission
    states are recorded from before the start."""
    from std_msgs.msg import Bool, String

    states = {r: TopicRecorder(names.absolute(names.robot_topic(r, names.MISSION_STATE)), String) for r in ROBOTS}
    graph = ros_master.attach()
    estop = rospy_node.Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
    estop.publish(Bool(False))  # the mux and the simulator hold until they hear the state
    try:
        graph.start_node(
            "cps_sim", "fleet_sim", name="fleet_sim", params={"~profile": "light", "~fleet_file": fleet_file}
        )
        graph.wait_for_topic(names.absolute(names.robot_topic("scout", names.POINTS)), timeout_s=60)
        for robot in ROBOTS:
            start_robot_nodes(graph, robot, fleet_file)
        yield states
    finally:
        graph.close()
        estop.unregister()
        for recorder in states.values():
            recorder.close()


@pytest.fixture
def record(running_fleet):
    """record(topic, type): a TopicRecorder closed after the test."""
    recorders = []

    def make(topic, msg_type, **kwargs):
        recorders.append(TopicRecorder(topic, msg_type, **kwargs))
        return recorders[-1]

    yield make
    for recorder in recorders:
        recorder.close()


def test_depth_clouds_are_organized_rgb_clouds_in_the_optical_frame(record, fleet):
    from sensor_msgs.msg import PointCloud2

    light = fleet.profile.depth_camera
    for robot in DEPTH_ROBOTS:
        cloud = record(names.absolute(names.robot_topic(robot, names.POINTS)), PointCloud2).wait(timeout_s=60)
        assert (cloud.height, cloud.width, cloud.point_step) == (light.height, light.width, 32)
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"] and not cloud.is_dense
        assert cloud.header.frame_id == f"{robot}/camera_depth_optical_frame"


def test_lidar_scan_is_an_unorganized_velodyne_cloud(record):
    from sensor_msgs.msg import PointCloud2

    scan = record(names.absolute(names.robot_topic("scout", names.POINTS)), PointCloud2).wait(timeout_s=60)
    assert scan.header.frame_id == "scout/lidar" and scan.height == 1
    assert [f.name for f in scan.fields] == ["x", "y", "z", "intensity", "ring", "time"]
    assert np.all(np.isfinite(cloud_to_array(scan)["x"]))


def test_camera_image_and_info_match_the_profile(record, fleet):
    from sensor_msgs.msg import CameraInfo, Image

    light = fleet.profile.depth_camera
    img = record(names.absolute(names.robot_topic("jackal", names.CAMERA_IMAGE)), Image).wait(timeout_s=30)
    assert (img.encoding, img.width, img.height) == ("rgb8", light.width, light.height)
    info = record(names.absolute(names.robot_topic("jackal", names.CAMERA_INFO)), CameraInfo).wait(timeout_s=30)
    assert info.K[0] > 0 and info.header.frame_id == "jackal/camera_depth_optical_frame"


def test_joints_battery_and_diagnostics(record):
    from diagnostic_msgs.msg import DiagnosticArray
    from sensor_msgs.msg import BatteryState, JointState

    assert (
        len(record(names.absolute(names.robot_topic("champ", names.JOINT_STATES)), JointState).wait(timeout_s=30).name)
        == 12
    )
    bat = record(names.absolute(names.robot_topic("scout", names.BATTERY)), BatteryState).wait(timeout_s=30)
    assert 0.0 < bat.percentage <= 1.0 and bat.voltage > 0 and bat.current < 0
    diag = record(names.DIAGNOSTICS, DiagnosticArray).wait(
        lambda m: any(s.name == "cps_sim: fleet" for s in m.status), timeout_s=10, what="fleet_sim's diagnostics"
    )
    statuses = [s.name for s in diag.status]
    assert "cps_sim: scout lidar" in statuses and "cps_sim: iris depth_camera" in statuses
    fleet_values = {kv.key: kv.value for kv in diag.status[statuses.index("cps_sim: fleet")].values}
    assert float(fleet_values["real_time_factor"]) > 0


def test_tf_map_to_odom_is_the_initial_pose_and_odometry_uses_the_robots_frames(record, fleet, rospy_node):
    import tf2_ros
    from nav_msgs.msg import Odometry

    rospy = rospy_node
    buffer = tf2_ros.Buffer()
    listener = tf2_ros.TransformListener(buffer)
    try:
        for robot in ROBOTS:
            msg = record(names.absolute(names.robot_topic(robot, names.ODOM)), Odometry).wait(timeout_s=30)
            assert (msg.header.frame_id, msg.child_frame_id) == (names.odom_frame(robot), names.base_frame(robot))
            pose = fleet.robot(robot).initial_pose
            static = buffer.lookup_transform(
                names.MAP_FRAME, names.odom_frame(robot), rospy.Time(0), rospy.Duration(10)
            )
            t = static.transform.translation
            assert (t.x, t.y) == pytest.approx((pose.x, pose.y), abs=1e-6)
            assert quat_yaw(static.transform.rotation) == pytest.approx(pose.yaw_rad, abs=1e-6)
            buffer.lookup_transform(names.MAP_FRAME, fleet.robot(robot).sensor_frame, rospy.Time(0), rospy.Duration(10))
    finally:
        del listener


def test_every_route_runs_to_done_through_inspecting(running_fleet, record, fleet, rospy_node):
    """Last in the module: the robots have finished their routes afterwards."""
    import tf2_ros
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import BatteryState

    rospy = rospy_node
    battery = record(names.absolute(names.robot_topic("scout", names.BATTERY)), BatteryState)
    odom = record(names.absolute(names.robot_topic("scout", names.ODOM)), Odometry)
    first_battery = battery.wait(timeout_s=30)
    for robot, states in running_fleet.items():
        states.wait(lambda m: m.data == "done", timeout_s=180, what=f"{robot}'s mission done")
    seen = {r: [m.data for _, m in s.messages] for r, s in running_fleet.items()}
    for robot in ROBOTS:
        assert "inspecting" in seen[robot], seen
    buffer = tf2_ros.Buffer()
    listener = tf2_ros.TransformListener(buffer)
    try:
        last = fleet.route("scout").waypoints[-1]
        map_to_base = buffer.lookup_transform(
            names.MAP_FRAME, names.base_frame("scout"), rospy.Time(0), rospy.Duration(5)
        )
    finally:
        del listener
    p = map_to_base.transform.translation
    assert math.hypot(p.x - last.x, p.y - last.y) < 0.6
    # At `done` it may still be braking (scout finishes last on these routes): it comes to rest.
    odom.wait(lambda m: abs(m.twist.twist.linear.x) < 0.05, timeout_s=10, what="scout at rest after done")
    assert (
        battery.wait(lambda m: m.percentage < first_battery.percentage, timeout_s=10).percentage
        < first_battery.percentage
    )


def test_every_cloud_has_its_robots_pose_on_tf_at_its_exact_stamp(record):
    """The twin places a cloud with its robot's tf at the cloud's stamp. Between two odometry
    samples tf interpolates; after a stall of the simulator's loop the samples around a capture lay
    up to 0.3 s apart while a turn accelerated, and the interpolated pose was degrees off (CI on
    1d27b42: the reference map knew voxels inside closed tanks). So each cloud's pose is on /tf
    at exactly its stamp."""
    from sensor_msgs.msg import PointCloud2
    from tf2_msgs.msg import TFMessage

    tf = record(names.TF, TFMessage, queue_size=None)
    tf.wait(timeout_s=10)  # connected: every cloud recorded from now on has its tf recorded too
    clouds = {
        r: record(names.absolute(names.robot_topic(r, names.POINTS)), PointCloud2, queue_size=None) for r in ROBOTS
    }
    for recorder in clouds.values():
        recorder.wait_count(4, timeout_s=30)
    time.sleep(0.5)  # the last cloud's tf may still be in flight on its own connection
    on_tf = {(t.child_frame_id, t.header.stamp.to_nsec()) for _, msg in list(tf.messages) for t in msg.transforms}
    for robot, recorder in clouds.items():
        stamps = [msg.header.stamp.to_nsec() for _, msg in list(recorder.messages)]
        missing = [s for s in stamps if (names.base_frame(robot), s) not in on_tf]
        assert stamps and not missing, (
            f"{robot}: {len(missing)} of {len(stamps)} clouds without a pose on {names.TF} at their stamp"
        )
