"""The ROS side of cps_sim: parameters, topics and timers wired to the pure library.

Three nodes use this: fleet_sim (`run_fleet_sim`), route_controller (`run_route_controller`)
and velocity_mux (`run_velocity_mux`).
"""
import math
import multiprocessing.connection
import sys
import threading
import time

import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist as TwistMsg
from nav_msgs.msg import Odometry
from sensor_msgs.msg import BatteryState, CameraInfo, Image, JointState, PointCloud2
from std_msgs.msg import Bool, String

from cps_msgs.config import ConfigError, load_yaml_document
from cps_msgs.fleet import load_fleet, robot_names_arg
from cps_sim import messages
from cps_sim.controllers import RouteFollower, VelocityMux, validate_route
from cps_sim.robots import Twist, pose_matrix, validate_twist
from cps_sim.scheduling import RateMeter, SensorScheduler
from cps_sim.sensor_workers import SensorWorkerPool
from cps_sim.simulation import FleetSimulation, sensor_points
from cps_sim.site import check_waypoint, load_site
from cps_sim.world import DEFAULT_RENDERER, RENDERERS

CMD_TIMEOUT_S = 0.5


def _fail(message):
    """Log a start-up error and exit non-zero (a clear message instead of a traceback)."""
    rospy.logfatal(message)
    sys.stderr.write(message + "\n")
    sys.stderr.flush()
    raise SystemExit(1)


def _positive_param(name, default):
    value = rospy.get_param(name, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        _fail(f"parameter {rospy.resolve_name(name)} must be a positive number, got {value!r}")
    return float(value)


def twist_from_msg(msg):
    return Twist(msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z)


def twist_to_msg(twist):
    msg = TwistMsg()
    msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z = twist.vx, twist.vy, twist.vz, twist.wz
    return msg


def load_fleet_param():
    """The fleet from ~fleet_file (and ~profile, ~robots), exiting with file:line on errors."""
    fleet_file = rospy.get_param("~fleet_file", "") or None
    profile = rospy.get_param("~profile", "") or None
    try:
        fleet = load_fleet(fleet_file, profile)
    except ConfigError as exc:
        _fail(f"bad fleet file: {exc}")
    robots = rospy.get_param("~robots", "")
    names = [n.strip() for n in str(robots).split(",") if n.strip()]
    try:
        return robot_names_arg(fleet, names)
    except ValueError as exc:
        _fail(f"parameter ~robots: {exc}")


def load_site_for(fleet):
    try:
        return load_site(fleet.site_path)
    except ConfigError as exc:
        _fail(f"bad site file: {exc}")


def apply_site_changes(site, without, moves):
    """The site with equipment removed (`without`: "a,b") and shifted (`moves`: "name:dx:dy,...")."""
    try:
        for name in [n.strip() for n in str(without).split(",") if n.strip()]:
            site = site.without(name)
        for move in [m.strip() for m in str(moves).split(",") if m.strip()]:
            parts = move.split(":")
            if len(parts) != 3:
                raise ValueError(f"'{move}' is not name:dx_m:dy_m")
            site = site.moved(parts[0], float(parts[1]), float(parts[2]))
    except (KeyError, ValueError) as exc:
        _fail(f"parameters ~site_without/~site_moves: {exc.args[0]}")
    return site


def check_initial_poses(fleet, site):
    """Exit naming fleet.yaml's line when an initial pose is outside the hall or in equipment."""
    doc = load_yaml_document(fleet.path)
    names = [r.get("name") for r in doc.data.get("robots", [])]
    for robot in fleet.robots:
        pose = robot.initial_pose
        reason = check_waypoint(site, pose.x, pose.y, max(pose.z, 0.0), robot.type, margin_m=0.2)
        if reason:
            line = doc.line(("robots", names.index(robot.name), "initial_pose"))
            _fail(f"bad fleet file: {ConfigError(fleet.path, line, f'robots[{robot.name}].initial_pose: {reason}')}")


# ------------------------------------------------------------------------------------------
# fleet_sim
# ------------------------------------------------------------------------------------------
class FleetSimNode:
    """All robots of the fleet in one world, publishing what their drivers would."""

    def __init__(self):
        self.fleet = load_fleet_param()
        renderer = rospy.get_param("~renderer", DEFAULT_RENDERER)
        if renderer not in RENDERERS:
            _fail(f"parameter ~renderer: unknown renderer '{renderer}' (known: {', '.join(RENDERERS)})")
        self.odom_rate_hz = _positive_param("~odom_rate_hz", 50.0)
        self.joint_rate_hz = _positive_param("~joint_state_rate_hz", 20.0)
        self.battery_rate_hz = _positive_param("~battery_rate_hz", 1.0)
        self.diagnostics_period_s = 1.0 / _positive_param("~diagnostics_rate_hz", 1.0)
        self.max_step_s = _positive_param("~max_physics_step_s", 0.02)
        self.max_catch_up_s = _positive_param("~max_catch_up_s", 1.0)
        workers = rospy.get_param("~sensor_workers", 2)
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            _fail(f"parameter {rospy.resolve_name('~sensor_workers')} must be an integer >= 0, got {workers!r}")
        self.site = apply_site_changes(load_site_for(self.fleet), rospy.get_param("~site_without", ""),
                                       rospy.get_param("~site_moves", ""))
        check_initial_poses(self.fleet, self.site)
        if workers > 0:
            # Robots' kinematics here; rendering and ray casting in worker processes.
            self.pool = SensorWorkerPool(self.fleet, self.site, renderer, workers)
            self.sim = FleetSimulation(self.fleet, site=self.site, renderer=None)
            self.renderer = self.pool.renderer
        else:
            self.pool = None
            self.sim = FleetSimulation(self.fleet, site=self.site, renderer=renderer)
            self.renderer = self.sim.renderer
        if renderer in ("fast", "egl") and self.renderer != renderer:  # 'auto' may choose tiny on purpose
            rospy.logwarn(f"renderer '{renderer}' unavailable (the sensor workers' log says why); "
                          f"using '{self.renderer}' (slower)")
        self.capture_ms = {name: 0.0 for name in self.sim.robots}
        self.lock = threading.Lock()
        self.pubs = {}
        self.cmd_time = {}
        self.bad_commands = {}
        for name, sim in self.sim.robots.items():
            pubs = {
                "points": rospy.Publisher(f"/{name}/points", PointCloud2, queue_size=2),
                "odom": rospy.Publisher(f"/{name}/odom", Odometry, queue_size=10),
                "joint_states": rospy.Publisher(f"/{name}/joint_states", JointState, queue_size=10),
                "battery": rospy.Publisher(f"/{name}/battery", BatteryState, queue_size=2),
            }
            if sim.config.has_depth_camera:
                pubs["image"] = rospy.Publisher(f"/{name}/camera/image_raw", Image, queue_size=2)
                pubs["info"] = rospy.Publisher(f"/{name}/camera/camera_info", CameraInfo, queue_size=2)
            self.pubs[name] = pubs
            self.cmd_time[name] = -math.inf
            self.bad_commands[name] = 0
            rospy.Subscriber(f"/{name}/cmd_vel", TwistMsg, self._on_cmd_vel, callback_args=name, queue_size=5)
            if sim.robot.is_aerial:
                rospy.Subscriber(f"/{name}/flight_command", String, self._on_flight_command, callback_args=name,
                                 queue_size=5)
        self.tf = tf2_ros.TransformBroadcaster()
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.diagnostics = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=5)
        now = time.time()
        statics = []
        for name, sim in self.sim.robots.items():
            statics.append(messages.transform_stamped(sim.robot.odom_in_map(), "map", f"{name}/odom", now))
            statics.append(messages.transform_stamped(sim.robot.sensor_in_base(), f"{name}/base_link",
                                                      sim.sensor_frame, now))
        self.static_tf.sendTransform(statics)
        self.scheduler = SensorScheduler({n: s.rate_hz for n, s in self.sim.robots.items()}, now)
        self.physics_meter = RateMeter()
        self.sim_time_s = 0.0
        self.wall_start_s = now
        self.rtf_window = []
        rospy.loginfo("fleet_sim: %s profile, renderer %s, %d sensor worker process(es), robots %s",
                      self.fleet.profile.name, self.renderer, workers, ", ".join(self.sim.robots))

    # Commands --------------------------------------------------------------------------------
    def _on_cmd_vel(self, msg, name):
        sim = self.sim.robots[name]
        twist = twist_from_msg(msg)
        reason = validate_twist(twist, sim.robot.spec.limits)
        with self.lock:
            if reason:
                self.bad_commands[name] += 1
                sim.robot.set_command(Twist())
                rospy.logwarn_throttle(2.0, f"/{name}/cmd_vel: dropped {reason}; holding "
                                            f"({self.bad_commands[name]} dropped so far)")
                return
            sim.robot.set_command(twist)
            self.cmd_time[name] = time.time()

    def _on_flight_command(self, msg, name):
        command = msg.data.strip().lower()
        with self.lock:
            if not self.sim.robots[name].robot.flight_command(command):
                rospy.logwarn_throttle(2.0, f"/{name}/flight_command: unknown command '{msg.data}' (known: takeoff, land)")

    # Loop ------------------------------------------------------------------------------------
    def _advance_physics(self, now):
        lag = now - (self.wall_start_s + self.sim_time_s)
        if lag > self.max_catch_up_s:
            # The loop stalled (a long render): drop the excess instead of jumping the robots.
            self.wall_start_s += lag - self.max_catch_up_s
            lag = self.max_catch_up_s
        with self.lock:
            for name, sim in self.sim.robots.items():
                if now - self.cmd_time[name] > CMD_TIMEOUT_S:
                    sim.robot.set_command(Twist())
            while lag > 1e-4:
                dt = min(lag, self.max_step_s)
                self.sim.step(dt)
                self.sim_time_s += dt
                lag -= dt
        self.physics_meter.tick(now)

    def _publish_state(self, now, joints, battery):
        transforms = []
        for name, sim in self.sim.robots.items():
            robot = sim.robot
            odom = messages.odometry(robot, now)
            self.pubs[name]["odom"].publish(odom)
            transforms.append(messages.transform_stamped(robot.base_in_odom(), f"{name}/odom", f"{name}/base_link", now))
            if joints:
                self.pubs[name]["joint_states"].publish(messages.joint_state(robot, now))
            if battery:
                self.pubs[name]["battery"].publish(messages.battery_state(robot, now))
        self.tf.sendTransform(transforms)

    def _publish_frame(self, name, frame, stamp):
        sim = self.sim.robots[name]
        pubs = self.pubs[name]
        pubs["points"].publish(messages.point_cloud2(sensor_points(frame), sim.sensor_frame, stamp))
        if "image" in pubs:
            pubs["image"].publish(messages.image_rgb8(frame.rgb, sim.sensor_frame, stamp))
            pubs["info"].publish(messages.camera_info(sim.sensor, sim.sensor_frame, stamp))

    def _record_capture_ms(self, name, ms):
        previous = self.capture_ms[name]
        self.capture_ms[name] = ms if previous == 0.0 else 0.8 * previous + 0.2 * ms

    def _capture_in_process(self, name):
        sim = self.sim.robots[name]
        with self.lock:
            sensor_pose = sim.robot.sensor_in_map()
        stamp = time.time()
        frame = sim.sensor.capture(sensor_pose)
        self._record_capture_ms(name, 1000.0 * (time.time() - stamp))
        self._publish_frame(name, frame, stamp)
        self.scheduler.done(name, stamp, time.time())

    def _service_workers(self, now):
        """Publish finished captures and hand due sensors to idle workers; True if any work was done."""
        worked = False
        for name, frame, requested, started, finished in self.pool.results():
            self._record_capture_ms(name, 1000.0 * (finished - started))
            self._publish_frame(name, frame, requested)
            self.scheduler.done(name, requested, time.time())
            worked = True
        while True:
            worker = self.pool.idle_worker()
            if worker is None:
                break
            name, due = self.scheduler.next(exclude=[w.busy_with for w in self.pool.workers if w.busy_with])
            if name is None or due > now:
                break
            with self.lock:
                poses = self.sim.poses()
            self.pool.request(worker, name, poses, time.time())
            worked = True
        return worked

    def _publish_diagnostics(self, now):
        array = DiagnosticArray()
        array.header.stamp = messages.stamp(now)
        wall = now - self._diag_wall_start
        rtf = (self.sim_time_s - self._diag_sim_start) / wall if wall > 0 else 1.0
        self._diag_wall_start, self._diag_sim_start = now, self.sim_time_s
        fleet_status = DiagnosticStatus(level=DiagnosticStatus.OK if rtf > 0.9 else DiagnosticStatus.WARN,
                                        name="cps_sim: fleet", hardware_id="fleet_sim",
                                        message=f"real-time factor {rtf:.2f}")
        fleet_status.values = [KeyValue("real_time_factor", f"{rtf:.3f}"), KeyValue("profile", self.fleet.profile.name),
                               KeyValue("renderer", str(self.renderer)),
                               KeyValue("sensor_workers", str(len(self.pool.workers) if self.pool else 0)),
                               KeyValue("physics_loop_hz", f"{self.physics_meter.rate_hz(now):.1f}")]
        array.status.append(fleet_status)
        summary = []
        for name, sim in self.sim.robots.items():
            achieved = self.scheduler.achieved_hz(name, now)
            ok = achieved >= 0.9 * sim.rate_hz
            kind = "lidar" if sim.config.has_lidar else "depth_camera"
            status = DiagnosticStatus(level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
                                      name=f"cps_sim: {name} {kind}", hardware_id=name,
                                      message=f"{achieved:.1f} of {sim.rate_hz:.1f} Hz")
            status.values = [KeyValue("configured_hz", f"{sim.rate_hz:.2f}"), KeyValue("achieved_hz", f"{achieved:.2f}"),
                             KeyValue("capture_ms", f"{self.capture_ms[name]:.1f}"),
                             KeyValue("skipped_captures", str(self.scheduler.skipped[name])),
                             KeyValue("dropped_commands", str(self.bad_commands[name])),
                             KeyValue("battery_percentage", f"{100 * sim.robot.battery_fraction:.1f}")]
            array.status.append(status)
            summary.append(f"{name} {achieved:.1f}/{sim.rate_hz:.1f} Hz")
        self.diagnostics.publish(array)
        rospy.loginfo_throttle(10.0, f"fleet_sim: achieved sensor rates {', '.join(summary)}; real-time factor {rtf:.2f}")

    def spin(self):
        odom_period = 1.0 / self.odom_rate_hz
        joint_period = 1.0 / self.joint_rate_hz
        battery_period = 1.0 / self.battery_rate_hz
        now = time.time()
        next_odom = next_joint = next_battery = now
        next_diag = now + self.diagnostics_period_s
        self._diag_wall_start, self._diag_sim_start = now, self.sim_time_s
        while not rospy.is_shutdown():
            now = time.time()
            self._advance_physics(now)
            if now >= next_odom:
                joints, battery = now >= next_joint, now >= next_battery
                self._publish_state(now, joints, battery)
                next_odom = max(next_odom + odom_period, now)
                if joints:
                    next_joint = max(next_joint + joint_period, now)
                if battery:
                    next_battery = max(next_battery + battery_period, now)
            if now >= next_diag:
                self._publish_diagnostics(now)
                next_diag = max(next_diag + self.diagnostics_period_s, now)
            if self.pool is not None:
                if self._service_workers(now):
                    continue
                self.pool.check_alive()
                name, due = self.scheduler.next(exclude=[w.busy_with for w in self.pool.workers if w.busy_with])
                if self.pool.idle_worker() is None:
                    due = float("inf")
                wake = min(due, next_odom, next_diag)
                busy = [w.conn for w in self.pool.workers if w.busy_with]
                delay = max(wake - time.time(), 0.0)
                if busy:
                    multiprocessing.connection.wait(busy, timeout=min(delay, odom_period))
                elif delay > 0:
                    time.sleep(min(delay, odom_period))
                continue
            name, due = self.scheduler.next()
            if name is not None and due <= now:
                self._capture_in_process(name)
                continue
            wake = min(due, next_odom, next_diag)
            delay = wake - time.time()
            if delay > 0:
                time.sleep(min(delay, odom_period))

    def close(self):
        if self.pool is not None:
            self.pool.close()
        self.sim.close()


def run_fleet_sim():
    rospy.init_node("fleet_sim")
    node = FleetSimNode()
    try:
        node.spin()
    finally:
        node.close()


# ------------------------------------------------------------------------------------------
# route_controller
# ------------------------------------------------------------------------------------------
class RouteControllerNode:
    """Follows the robot's route from its odometry and the known initial pose (in /<r>)."""

    def __init__(self):
        fleet = load_fleet_param()
        name = rospy.get_param("~robot", "")
        if not name:
            _fail("parameter ~robot is required (the robot's name in the fleet file)")
        try:
            self.config = fleet.robot(name)
        except KeyError as exc:
            _fail(f"parameter ~robot: {exc.args[0]}")
        site = load_site_for(fleet)
        try:
            route = fleet.route(name)
            validate_route(route, site, self.config.type)
        except ConfigError as exc:
            _fail(f"bad route file: {exc}")
        self.rate_hz = _positive_param("~rate_hz", 10.0)
        pose = self.config.initial_pose
        self.odom_in_map = pose_matrix(pose.x, pose.y, pose.z, pose.yaw_rad)
        self.follower = RouteFollower(route, self.config.type, start_xy=(pose.x, pose.y))
        self.cmd_pub = rospy.Publisher("cmd_vel/auto", TwistMsg, queue_size=5)
        self.state_pub = rospy.Publisher("mission_state", String, queue_size=1, latch=True)
        self.flight_pub = rospy.Publisher("flight_command", String, queue_size=5)
        self.pose = None
        self.last_state = None
        self._publish_state()
        rospy.Subscriber("odom", Odometry, self._on_odom, queue_size=5)
        rospy.loginfo("route_controller %s: %d waypoints from %s", name, len(route.waypoints), route.path)

    def _on_odom(self, msg):
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        yaw_odom = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        m = self.odom_in_map @ pose_matrix(p.x, p.y, p.z, yaw_odom)
        self.pose = (m[0, 3], m[1, 3], m[2, 3], math.atan2(m[1, 0], m[0, 0]))

    def _publish_state(self):
        state = self.follower.state
        if state != self.last_state:
            self.state_pub.publish(String(state))
            rospy.loginfo("route_controller %s: mission %s", self.config.name, state)
            self.last_state = state

    def spin(self):
        rate = rospy.Rate(self.rate_hz)
        while not rospy.is_shutdown():
            if self.pose is not None:
                twist, flight = self.follower.update(*self.pose)
                if flight:
                    self.flight_pub.publish(String(flight))
                if not self.follower.finished or self.last_state != "done":
                    self.cmd_pub.publish(twist_to_msg(twist))
                self._publish_state()
            try:
                rate.sleep()
            except rospy.ROSInterruptException:
                break


def run_route_controller():
    rospy.init_node("route_controller")
    RouteControllerNode().spin()


# ------------------------------------------------------------------------------------------
# velocity_mux
# ------------------------------------------------------------------------------------------
class VelocityMuxNode:
    """cmd_vel/auto or cmd_vel/teleop by control_mode -> cmd_vel, with dead-man and e-stop (in /<r>)."""

    def __init__(self):
        fleet = load_fleet_param()
        name = rospy.get_param("~robot", "") or rospy.get_namespace().strip("/")
        try:
            self.config = fleet.robot(name)
        except KeyError as exc:
            _fail(f"parameter ~robot: {exc.args[0]}")
        self.rate_hz = _positive_param("~rate_hz", 20.0)
        deadman = _positive_param("~deadman_s", 0.5)
        self.mux = VelocityMux(self.config.type, deadman_s=deadman)
        self.lock = threading.Lock()
        self.pub = rospy.Publisher("cmd_vel", TwistMsg, queue_size=5)
        # The mode in force (yocs_cmd_vel_mux's `active`): control_mode is only what was asked.
        self.active_pub = rospy.Publisher("control_mode/active", String, queue_size=1, latch=True)
        self.active_pub.publish(String(data=self.mux.mode))
        rospy.Subscriber("cmd_vel/auto", TwistMsg, self._on_cmd, callback_args="auto", queue_size=5)
        rospy.Subscriber("cmd_vel/teleop", TwistMsg, self._on_cmd, callback_args="teleop", queue_size=5)
        rospy.Subscriber("control_mode", String, self._on_mode, queue_size=5)
        rospy.Subscriber("/fleet/estop", Bool, self._on_estop, queue_size=5)

    def _on_cmd(self, msg, source):
        with self.lock:
            now = time.time()
            handler = self.mux.on_auto if source == "auto" else self.mux.on_teleop
            reason = handler(twist_from_msg(msg), now)
        if reason:
            rospy.logwarn_throttle(2.0, f"{rospy.resolve_name('cmd_vel/' + source)}: dropped {reason}; holding "
                                        f"({self.mux.dropped} dropped so far)")

    def _on_mode(self, msg):
        try:
            with self.lock:
                self.mux.set_mode(msg.data.strip())
            self.active_pub.publish(String(data=self.mux.mode))
            rospy.loginfo("velocity_mux %s: control mode %s", self.config.name, self.mux.mode)
        except ValueError as exc:
            rospy.logwarn_throttle(2.0, f"{rospy.resolve_name('control_mode')}: {exc}; staying in {self.mux.mode}")

    def _on_estop(self, msg):
        with self.lock:
            self.mux.set_estop(msg.data)

    def spin(self):
        rate = rospy.Rate(self.rate_hz)
        while not rospy.is_shutdown():
            with self.lock:
                out = self.mux.update(time.time())
            self.pub.publish(twist_to_msg(out))
            try:
                rate.sleep()
            except rospy.ROSInterruptException:
                break


def run_velocity_mux():
    rospy.init_node("velocity_mux")
    VelocityMuxNode().spin()


__all__ = ["run_fleet_sim", "run_route_controller", "run_velocity_mux"]
