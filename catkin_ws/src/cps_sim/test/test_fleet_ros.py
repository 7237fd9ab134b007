"""The nodes on a real master: the default fleet runs its routes to `done` in the light profile
and publishes the contract's topics and frames; the dead-man, mode switch, e-stop and bad
inputs behave as the issue states."""
import math
import threading
import time

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_sim.messages import cloud_to_array

pytestmark = pytest.mark.ros

ROBOTS = ("scout", "jackal", "champ", "iris")


class Latest:
    """The last message of a topic, and an event set when one arrives."""

    def __init__(self, rospy, topic, msg_type, keep=False):
        self.msg, self.all, self.event = None, [], threading.Event()
        self.keep = keep
        self.sub = rospy.Subscriber(topic, msg_type, self._on, queue_size=5)

    def _on(self, msg):
        self.msg = msg
        if self.keep:
            self.all.append(msg)
        self.event.set()

    def wait(self, timeout_s=30.0):
        assert self.event.wait(timeout_s), f"nothing on {self.sub.name} within {timeout_s} s"
        return self.msg

    def close(self):
        self.sub.unregister()


def _start_robot_nodes(ros, name):
    ros.start_node("cps_sim", "velocity_mux", name="velocity_mux", namespace=f"/{name}", params={"~robot": name})
    ros.start_node("cps_sim", "route_controller", name="route_controller", namespace=f"/{name}",
                   params={"~robot": name})


def _quat_yaw(q):
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def test_default_fleet_runs_routes_to_done_with_contract_topics(ros, rospy_node):
    rospy = rospy_node
    import tf2_ros
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from sensor_msgs.msg import BatteryState, CameraInfo, Image, JointState, PointCloud2
    from std_msgs.msg import String

    fleet = load_fleet(profile="light")
    states = {r: Latest(rospy, f"/{r}/mission_state", String, keep=True) for r in ROBOTS}
    ros.start_node("cps_sim", "fleet_sim", name="fleet_sim", params={"~profile": "light"})
    ros.wait_for_topic("/scout/points", timeout_s=60)
    for robot in ROBOTS:
        _start_robot_nodes(ros, robot)

    buffer = tf2_ros.Buffer()
    listener = tf2_ros.TransformListener(buffer)
    clouds = {r: Latest(rospy, f"/{r}/points", PointCloud2) for r in ROBOTS}
    image = Latest(rospy, "/jackal/camera/image_raw", Image)
    info = Latest(rospy, "/jackal/camera/camera_info", CameraInfo)
    odom = {r: Latest(rospy, f"/{r}/odom", Odometry) for r in ROBOTS}
    joints = Latest(rospy, "/champ/joint_states", JointState)
    battery = Latest(rospy, "/scout/battery", BatteryState)
    diagnostics = Latest(rospy, "/diagnostics", DiagnosticArray)
    try:
        light = fleet.profile.depth_camera
        for robot in ("jackal", "champ", "iris"):
            cloud = clouds[robot].wait(60)
            assert (cloud.height, cloud.width, cloud.point_step) == (light.height, light.width, 32)
            assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"] and not cloud.is_dense
            assert cloud.header.frame_id == f"{robot}/camera_depth_optical_frame"
        scan = clouds["scout"].wait(60)
        assert scan.header.frame_id == "scout/lidar" and scan.height == 1
        assert [f.name for f in scan.fields] == ["x", "y", "z", "intensity", "ring", "time"]
        assert np.all(np.isfinite(cloud_to_array(scan)["x"]))
        img = image.wait()
        assert (img.encoding, img.width, img.height) == ("rgb8", light.width, light.height)
        assert info.wait().K[0] > 0 and info.msg.header.frame_id == "jackal/camera_depth_optical_frame"
        assert len(joints.wait().name) == 12
        bat = battery.wait()
        assert 0.0 < bat.percentage <= 1.0 and bat.voltage > 0 and bat.current < 0
        diag = diagnostics.wait(10)
        names = [s.name for s in diag.status]
        assert "cps_sim: fleet" in names and "cps_sim: scout lidar" in names and "cps_sim: iris depth_camera" in names
        fleet_values = {kv.key: kv.value for kv in diag.status[names.index("cps_sim: fleet")].values}
        assert float(fleet_values["real_time_factor"]) > 0

        # tf: map -> <r>/odom is the initial pose; map -> base_link composes it with odometry.
        for robot in ROBOTS:
            msg = odom[robot].wait()
            assert (msg.header.frame_id, msg.child_frame_id) == (f"{robot}/odom", f"{robot}/base_link")
            pose = fleet.robot(robot).initial_pose
            static = buffer.lookup_transform("map", f"{robot}/odom", rospy.Time(0), rospy.Duration(10))
            t = static.transform.translation
            assert (t.x, t.y) == pytest.approx((pose.x, pose.y), abs=1e-6)
            assert _quat_yaw(static.transform.rotation) == pytest.approx(pose.yaw_rad, abs=1e-6)
            frame = fleet.robot(robot).sensor_frame
            buffer.lookup_transform("map", frame, rospy.Time(0), rospy.Duration(10))

        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and not all(s.msg is not None and s.msg.data == "done" for s in states.values()):
            time.sleep(0.5)
        seen = {r: [m.data for m in s.all] for r, s in states.items()}
        for robot in ROBOTS:
            assert seen[robot] and seen[robot][-1] == "done", seen
            assert "inspecting" in seen[robot], seen
        final = odom["scout"].wait()
        last = fleet.route("scout").waypoints[-1]
        map_to_base = buffer.lookup_transform("map", "scout/base_link", rospy.Time(0), rospy.Duration(5))
        p = map_to_base.transform.translation
        assert math.hypot(p.x - last.x, p.y - last.y) < 0.6
        assert abs(final.twist.twist.linear.x) < 0.05
        assert battery.msg.percentage < bat.percentage
    finally:
        for sub in [*clouds.values(), image, info, *odom.values(), joints, battery, diagnostics, *states.values()]:
            sub.close()
        del listener


def test_deadman_mode_switch_estop_and_bad_commands(ros, rospy_node):
    rospy = rospy_node
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry
    from std_msgs.msg import Bool, String

    # Captures in the node's own process here (~sensor_workers 0); the fleet test uses workers.
    ros.start_node("cps_sim", "fleet_sim", name="fleet_sim_jackal",
                   params={"~profile": "light", "~robots": "jackal", "~sensor_workers": 0})
    ros.wait_for_topic("/jackal/odom", timeout_s=60)
    _start_robot_nodes(ros, "jackal")
    odom = Latest(rospy, "/jackal/odom", Odometry)
    executed = Latest(rospy, "/jackal/cmd_vel", Twist)
    state = Latest(rospy, "/jackal/mission_state", String)
    mode = rospy.Publisher("/jackal/control_mode", String, queue_size=1, latch=True)
    teleop = rospy.Publisher("/jackal/cmd_vel/teleop", Twist, queue_size=5)
    direct = rospy.Publisher("/jackal/cmd_vel", Twist, queue_size=5)
    estop = rospy.Publisher("/fleet/estop", Bool, queue_size=1, latch=True)

    def wait_for(predicate, timeout_s, what):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if predicate():
                return time.monotonic()
            time.sleep(0.02)
        raise AssertionError(f"{what} within {timeout_s} s")

    def moving():
        return odom.msg is not None and abs(odom.msg.twist.twist.linear.x) > 0.05 or (
            odom.msg is not None and abs(odom.msg.twist.twist.angular.z) > 0.05)

    def stopped():
        return odom.msg is not None and abs(odom.msg.twist.twist.linear.x) < 1e-3 and abs(odom.msg.twist.twist.angular.z) < 1e-3

    try:
        wait_for(lambda: state.msg is not None and state.msg.data in ("transit", "inspecting"), 30, "mission started")
        wait_for(moving, 20, "robot moving on its route")
        mode.publish(String("teleop"))
        wait_for(stopped, 5, "teleop without commands stops the robot")
        # Teleop drives; then the operator lets go: the dead-man stops the robot.
        forward = Twist()
        forward.linear.x = 0.3
        for _ in range(15):
            teleop.publish(forward)
            time.sleep(0.1)
        assert executed.wait().linear.x == pytest.approx(0.3, abs=0.05)
        released = time.monotonic()
        stop_t = wait_for(lambda: executed.msg.linear.x == 0.0, 3, "dead-man zeroes cmd_vel")
        assert stop_t - released < 1.2
        wait_for(stopped, 3, "robot stopped after the dead-man")
        _assert_cloud_lands_in_the_hall_via_tf(rospy, "jackal")

        # NaN and absurd teleop commands are dropped; the robot holds.
        for bad in (float("nan"), 1e6):
            cmd = Twist()
            cmd.linear.x = bad
            for _ in range(5):
                teleop.publish(cmd)
                time.sleep(0.05)
        assert stopped() and executed.msg.linear.x == 0.0
        wait_for(lambda: "dropped" in ros.output("velocity_mux"), 5, "mux warns about dropped commands")
        # A NaN straight to the robot's cmd_vel is dropped by the simulator too.
        nan = Twist()
        nan.angular.z = float("inf")
        direct.publish(nan)
        wait_for(lambda: "dropped" in ros.output("fleet_sim_jackal"), 5, "fleet_sim warns about dropped commands")
        assert stopped()

        # Back to auto: the route takes control again.
        mode.publish(String("auto"))
        wait_for(moving, 10, "route takes over after the mode switch")
        estop.publish(Bool(True))
        wait_for(lambda: executed.msg.linear.x == 0.0 and executed.msg.angular.z == 0.0, 3, "e-stop zeroes cmd_vel")
        wait_for(stopped, 3, "robot stopped by e-stop")
        estop.publish(Bool(False))
        wait_for(moving, 10, "robot resumes after e-stop release")
    finally:
        for sub in (odom, executed, state):
            sub.close()
        for pub in (mode, teleop, direct, estop):
            pub.unregister()


def _assert_cloud_lands_in_the_hall_via_tf(rospy, robot):
    """Points of a published cloud, moved to `map` with the published tf, lie on the floor
    (z = 0) or inside the hall's walls: the whole chain map -> odom -> base_link -> optical
    frame agrees with what the sensor saw."""
    import tf2_ros
    from sensor_msgs.msg import PointCloud2

    buffer = tf2_ros.Buffer()
    listener = tf2_ros.TransformListener(buffer)
    listening_since = rospy.Time.now()
    cloud = Latest(rospy, f"/{robot}/points", PointCloud2)
    try:
        msg = cloud.wait(30)
        while msg.header.stamp < listening_since + rospy.Duration(0.5):   # tf must cover the stamp
            cloud.event.clear()
            msg = cloud.wait(30)
        tf = buffer.lookup_transform("map", msg.header.frame_id, msg.header.stamp, rospy.Duration(10))
    finally:
        cloud.close()
        del listener
    q, t = tf.transform.rotation, tf.transform.translation
    x, y, z, w = q.x, q.y, q.z, q.w
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                    [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                    [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
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
    bad.write_text(text.replace("routes/", f"{fleet.path.rsplit('/', 1)[0]}/routes/").replace(
        "../../cps_sim/config/hall.yaml", fleet.site_path))
    proc = ros.start_node("cps_sim", "fleet_sim", name="fleet_sim_bad", params={"~fleet_file": str(bad)})
    assert _wait_exit(proc) != 0
    out = ros.output("fleet_sim_bad")
    line = next(i for i, l in enumerate(text.splitlines(), 1) if "hexapod" in l)
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
    proc = ros.start_node("cps_sim", "route_controller", name="route_bad", namespace="/scout",
                          params={"~robot": "scout", "~fleet_file": str(path)})
    assert _wait_exit(proc) != 0
    out = ros.output("route_bad")
    assert f"{routes / 'route1.yaml'}:3:" in out and "tank_1" in out


def test_site_change_with_unknown_item_fails_naming_the_known_ones(ros):
    proc = ros.start_node("cps_sim", "fleet_sim", name="fleet_sim_badsite",
                          params={"~robots": "jackal", "~site_moves": "crate_99:1.0:0.0"})
    assert _wait_exit(proc) != 0
    out = ros.output("fleet_sim_badsite")
    assert "crate_99" in out and "crate_2" in out
