"""cps_sim's nodes for one robot on a real master: teleop and the dead-man, bad commands, mode
switch and e-stop; and the start-up errors that name the file and line."""

import numpy as np
import pytest
from rostest_support import start_robot_nodes

from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_harness.testing import TopicRecorder, wait_for
from cps_sim.messages import cloud_to_array

pytestmark = pytest.mark.ros


class Jackal:
    """jackal alone (captures in the node's process, ~sensor_workers 0) with its mux and route
    controller, recorders of what it executes and publishers of what an operator sends."""

    def __init__(self, graph, rospy):
        from geometry_msgs.msg import Twist
        from nav_msgs.msg import Odometry
        from std_msgs.msg import Bool, String

        self.graph = graph
        graph.start_node(
            "cps_sim",
            "fleet_sim",
            name="fleet_sim_jackal",
            params={"~profile": "light", "~robots": "jackal", "~sensor_workers": 0},
        )
        graph.wait_for_topic(names.absolute(names.robot_topic("jackal", names.ODOM)), timeout_s=60)
        start_robot_nodes(graph, "jackal")
        self.odom = TopicRecorder(names.absolute(names.robot_topic("jackal", names.ODOM)), Odometry)
        self.executed = TopicRecorder(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), Twist)
        self.state = TopicRecorder(names.absolute(names.robot_topic("jackal", names.MISSION_STATE)), String)
        self.active_mode = TopicRecorder(names.absolute(names.robot_topic("jackal", names.CONTROL_MODE_ACTIVE)), String)
        self.mode = rospy.Publisher(
            names.absolute(names.robot_topic("jackal", names.CONTROL_MODE)), String, queue_size=1, latch=True
        )
        self.teleop = rospy.Publisher(
            names.absolute(names.robot_topic("jackal", names.CMD_VEL_TELEOP)), Twist, queue_size=5
        )
        self.direct = rospy.Publisher(names.absolute(names.robot_topic("jackal", names.CMD_VEL)), Twist, queue_size=5)
        self.estop = rospy.Publisher(names.ESTOP, Bool, queue_size=1, latch=True)
        self.estop.publish(Bool(False))  # the mux and the simulator hold until they hear the state

    def set_mode(self, mode):
        from std_msgs.msg import String

        self.mode.publish(String(mode))
        self.active_mode.wait(lambda m: m.data == mode, timeout_s=10, what=f"the mux in {mode}")

    def wait_moving(self, timeout_s, what):
        twist = lambda m: m.twist.twist  # noqa: E731
        self.odom.wait(
            lambda m: abs(twist(m).linear.x) > 0.05 or abs(twist(m).angular.z) > 0.05, timeout_s=timeout_s, what=what
        )

    def wait_stopped(self, timeout_s, what):
        twist = lambda m: m.twist.twist  # noqa: E731
        self.odom.wait(
            lambda m: abs(twist(m).linear.x) < 1e-3 and abs(twist(m).angular.z) < 1e-3, timeout_s=timeout_s, what=what
        )

    def close(self):
        for recorder in (self.odom, self.executed, self.state, self.active_mode):
            recorder.close()
        for pub in (self.mode, self.teleop, self.direct, self.estop):
            pub.unregister()
        self.graph.close()


@pytest.fixture(scope="module")
def jackal(ros_master, rospy_node):
    robot = Jackal(ros_master.attach(), rospy_node)
    try:
        robot.state.wait(lambda m: m.data in ("transit", "inspecting"), timeout_s=30, what="mission started")
        robot.wait_moving(20, "robot moving on its route")
        yield robot
    finally:
        robot.close()


def _twist(**axes):
    from geometry_msgs.msg import Twist

    msg = Twist()
    msg.linear.x = axes.get("x", 0.0)
    msg.angular.z = axes.get("wz", 0.0)
    return msg


def test_teleop_without_commands_holds_then_drives_and_the_deadman_stops_it(jackal, rospy_node):
    jackal.set_mode("teleop")
    jackal.wait_stopped(5, "teleop without commands stops the robot")
    rate = rospy_node.Rate(10)
    for _ in range(15):
        jackal.teleop.publish(_twist(x=0.3))
        rate.sleep()
    jackal.executed.wait(
        lambda m: m.linear.x == pytest.approx(0.3, abs=0.05), timeout_s=0.4, what="the teleop command executed"
    )
    jackal.executed.wait(lambda m: m.linear.x == 0.0, timeout_s=3, what="the dead-man zeroing cmd_vel")
    jackal.wait_stopped(3, "robot stopped after the dead-man")
    _assert_cloud_lands_in_the_hall_via_tf(rospy_node, "jackal")


def test_nan_and_absurd_teleop_commands_are_dropped_and_the_robot_holds(jackal):
    jackal.set_mode("teleop")
    jackal.wait_stopped(5, "teleop without commands stops the robot")
    for bad in (float("nan"), 1e6):
        jackal.teleop.publish(_twist(x=bad))
        assert wait_for(lambda: ros_output_count(jackal, "velocity_mux", "dropped") > 0, 5), (
            "mux warns about dropped commands"
        )
    jackal.executed.wait(lambda m: m.linear.x == 0.0, timeout_s=3, what="cmd_vel holding at zero")
    jackal.wait_stopped(3, "the robot holding")


def test_a_non_finite_command_straight_to_the_robot_is_dropped_by_the_simulator(jackal):
    jackal.set_mode("teleop")
    jackal.direct.publish(_twist(wz=float("inf")))
    assert wait_for(lambda: ros_output_count(jackal, "fleet_sim_jackal", "dropped") > 0, 5), (
        "fleet_sim warns about dropped commands"
    )
    jackal.wait_stopped(3, "the robot holding")


def test_auto_takes_over_after_the_mode_switch_and_estop_stops_until_released(jackal):
    from std_msgs.msg import Bool

    jackal.set_mode("auto")
    jackal.wait_moving(10, "route takes over after the mode switch")
    jackal.estop.publish(Bool(True))
    jackal.executed.wait(lambda m: m.linear.x == 0.0 and m.angular.z == 0.0, timeout_s=3, what="e-stop zeroing cmd_vel")
    jackal.wait_stopped(3, "robot stopped by e-stop")
    jackal.estop.publish(Bool(False))
    jackal.wait_moving(10, "robot resumes after e-stop release")


def ros_output_count(robot, node, text):
    return robot.graph.output(node).count(text)


def _assert_cloud_lands_in_the_hall_via_tf(rospy, robot):
    """Points of a published cloud, moved to `map` with the published tf, lie on the floor
    (z = 0) or inside the hall's walls: the whole chain map -> odom -> base_link -> optical
    frame agrees with what the sensor saw."""
    import tf2_ros
    from sensor_msgs.msg import PointCloud2

    buffer = tf2_ros.Buffer()
    listener = tf2_ros.TransformListener(buffer)
    listening_since = rospy.Time.now()
    cloud = TopicRecorder(names.absolute(names.robot_topic(robot, names.POINTS)), PointCloud2)
    try:
        # tf must cover the stamp
        msg = cloud.wait(
            lambda m: m.header.stamp >= listening_since + rospy.Duration(0.5),
            timeout_s=30,
            what="a cloud stamped after tf is heard",
        )
        tf = buffer.lookup_transform(names.MAP_FRAME, msg.header.frame_id, msg.header.stamp, rospy.Duration(10))
    finally:
        cloud.close()
        del listener
    q, t = tf.transform.rotation, tf.transform.translation
    x, y, z, w = q.x, q.y, q.z, q.w
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    points = cloud_to_array(msg).reshape(-1)
    xyz = np.stack([points["x"], points["y"], points["z"]], axis=1).astype(float)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    world = xyz @ rot.T + [t.x, t.y, t.z]
    assert len(world) > 1000
    assert world[:, 2].min() > -0.05
    assert np.all((world[:, 0] > -10.25) & (world[:, 0] < 10.25) & (world[:, 1] > -7.75) & (world[:, 1] < 7.75))
    floor = np.abs(world[:, 2]) < 0.02
    assert floor.mean() > 0.2, f"only {floor.mean():.0%} of the points are on the floor"


def _wait_exit(proc, timeout_s=60):
    proc.wait(timeout_s)
    return proc.returncode


def test_malformed_fleet_file_fails_with_file_and_line(ros, tmp_path):
    fleet = load_fleet()
    text = open(fleet.path).read().replace("type: legged_depth", "type: hexapod", 1)
    bad = tmp_path / "fleet.yaml"
    bad.write_text(
        text.replace("routes/", f"{fleet.path.rsplit('/', 1)[0]}/routes/").replace(
            "../../cps_sim/config/hall.yaml", fleet.site_path
        )
    )
    proc = ros.start_node("cps_sim", "fleet_sim", name="fleet_sim_bad", params={"~fleet_file": str(bad)})
    assert _wait_exit(proc) != 0
    out = ros.output("fleet_sim_bad")
    line = next(i for i, text_line in enumerate(text.splitlines(), 1) if "hexapod" in text_line)
    assert f"{bad}:{line}:" in out and "hexapod" in out
    for known in ("wheeled_lidar", "wheeled_depth", "legged_depth", "aerial_depth"):
        assert known in out


def test_route_with_waypoint_in_equipment_fails_with_file_and_line(ros, tmp_path):
    fleet = load_fleet()
    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "route1.yaml").write_text("waypoints:\n  - {x: -8.5, y: -4.0}\n  - {x: -5.6, y: -3.5, inspect: true}\n")
    text = open(fleet.path).read().replace("../../cps_sim/config/hall.yaml", fleet.site_path)
    for k in (2, 3, 4):
        text = text.replace(f"routes/route{k}.yaml", f"{fleet.path.rsplit('/', 1)[0]}/routes/route{k}.yaml")
    path = tmp_path / "fleet.yaml"
    path.write_text(text)
    proc = ros.start_node(
        "cps_sim",
        "route_controller",
        name="route_bad",
        namespace=names.absolute("scout"),
        params={"~robot": "scout", "~fleet_file": str(path)},
    )
    assert _wait_exit(proc) != 0
    out = ros.output("route_bad")
    assert f"{routes / 'route1.yaml'}:3:" in out and "tank_1" in out


def test_site_change_with_unknown_item_fails_naming_the_known_ones(ros):
    proc = ros.start_node(
        "cps_sim",
        "fleet_sim",
        name="fleet_sim_badsite",
        params={"~robots": "jackal", "~site_moves": "crate_99:1.0:0.0"},
    )
    assert _wait_exit(proc) != 0
    out = ros.output("fleet_sim_badsite")
    assert "crate_99" in out and "crate_2" in out


def test_site_changes_file_out_of_the_hall_fails_with_file_and_line(ros, tmp_path):
    changes = tmp_path / "changes.yaml"
    changes.write_text("moved:\n  - {name: crate_2, dx_m: 20.0}\n")
    proc = ros.start_node(
        "cps_sim",
        "fleet_sim",
        name="fleet_sim_badchanges",
        params={"~robots": "jackal", "~site_changes_file": str(changes)},
    )
    assert _wait_exit(proc) != 0
    out = ros.output("fleet_sim_badchanges")
    assert f"{changes}:2:" in out and "would leave the hall" in out, out[-2000:]
