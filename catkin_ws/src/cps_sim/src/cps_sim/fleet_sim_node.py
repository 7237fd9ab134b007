"""fleet_sim's ROS side: every robot of the fleet in one world, publishing what its drivers would.

Parameters are read once into `FleetSimOptions`; the loop is `cps_sim.realtime.run_realtime`
over `FleetSimNode.step`.
"""

import dataclasses
import math
import multiprocessing.connection
import threading
import time
from typing import Tuple

import rospy
import tf2_ros
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Twist as TwistMsg
from nav_msgs.msg import Odometry
from sensor_msgs.msg import BatteryState, CameraInfo, Image, JointState, PointCloud2
from std_msgs.msg import Bool, String

from cps_fleet import names
from cps_fleet.config import ConfigError
from cps_fleet.site import check_waypoint
from cps_ros.publisher import Publisher
from cps_ros.shutdown import init_node
from cps_sim import messages
from cps_sim.controllers import CommandGate
from cps_sim.node_support import fail, load_fleet_param, load_site_for, name_list, positive_param, twist_from_msg
from cps_sim.realtime import Periodic, PhysicsClock, run_realtime
from cps_sim.renderers import DEFAULT_RENDERER, RENDERERS
from cps_sim.robots import Twist, validate_twist
from cps_sim.scheduling import RateMeter, SensorScheduler, StepTimer
from cps_sim.sensor_workers import SensorWorkerPool
from cps_sim.simulation import FleetSimulation, sensor_points
from cps_sim.site_changes import SiteMove, apply_site_changes, load_site_changes
from cps_sim.video import video_level_errors
from cps_sim.video_ros import RobotVideo
from cps_sim.video_trace import VideoTraceError, VideoTracePlayer, load_video_trace

CMD_TIMEOUT_S = 0.5
# The recorded videos' thread looks at its schedule at least this often (s).
VIDEO_POLL_S = 0.02


@dataclasses.dataclass(frozen=True)
class FleetSimOptions:
    """fleet_sim's private parameters, checked (see the README for their meaning)."""

    renderer: str = DEFAULT_RENDERER
    odom_rate_hz: float = 50.0
    joint_state_rate_hz: float = 20.0
    battery_rate_hz: float = 1.0
    diagnostics_rate_hz: float = 1.0
    max_physics_step_s: float = 0.02
    max_catch_up_s: float = 1.0
    sensor_workers: int = 2
    site_without: Tuple[str, ...] = ()
    site_moves: Tuple[SiteMove, ...] = ()
    site_changes_file: str = ""
    # No bandwidth manager: every camera's video at the finest level and the fleet's maximum rate
    # (the unmanaged load), not the coarse default it keeps until a manager speaks.
    video_unmanaged: bool = False
    # A recorded video trace (cps_sim.video_trace) the cameras play instead of rendering; "": render live.
    video_trace: str = ""


def read_options():
    """FleetSimOptions from the private parameters; a bad one stops the node naming it."""
    default = FleetSimOptions()
    renderer = rospy.get_param("~renderer", default.renderer)
    if renderer not in RENDERERS:
        fail(f"parameter ~renderer: unknown renderer '{renderer}' (known: {', '.join(RENDERERS)})")
    rates = {
        field: positive_param(f"~{field}", getattr(default, field))
        for field in (
            "odom_rate_hz",
            "joint_state_rate_hz",
            "battery_rate_hz",
            "diagnostics_rate_hz",
            "max_physics_step_s",
            "max_catch_up_s",
        )
    }
    workers = rospy.get_param("~sensor_workers", default.sensor_workers)
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
        fail(f"parameter {rospy.resolve_name('~sensor_workers')} must be an integer >= 0, got {workers!r}")
    try:
        moves = tuple(SiteMove.parse(m) for m in name_list(rospy.get_param("~site_moves", "")))
    except ValueError as exc:
        fail(f"parameters ~site_without/~site_moves: {exc.args[0]}")
    return FleetSimOptions(
        renderer=renderer,
        sensor_workers=workers,
        site_without=tuple(name_list(rospy.get_param("~site_without", ""))),
        site_moves=moves,
        site_changes_file=rospy.get_param("~site_changes_file", ""),
        video_unmanaged=bool(rospy.get_param("~video_unmanaged", default.video_unmanaged)),
        video_trace=str(rospy.get_param("~video_trace", default.video_trace)),
        **rates,
    )


def initial_pose_error(fleet, site):
    """A ConfigError at the fleet file's line for an initial pose outside the hall or in equipment, or None."""
    for robot in fleet.robots:
        pose = robot.initial_pose
        reason = check_waypoint(site, pose.x, pose.y, max(pose.z, 0.0), robot.robot_type, margin_m=0.2)
        if reason:
            path, line = robot.source
            return ConfigError(path or fleet.path, line, f"robots[{robot.name}].initial_pose: {reason}")
    return None


class FleetSimNode:
    """All robots of the fleet in one world, publishing what their drivers would."""

    def __init__(self, fleet, options: FleetSimOptions):
        self.fleet = fleet
        self.options = options
        try:
            self.site = apply_site_changes(load_site_for(fleet), options.site_without, options.site_moves)
        except KeyError as exc:
            fail(f"parameters ~site_without/~site_moves: {exc.args[0]}")
        if options.site_changes_file:
            try:
                changes = load_site_changes(options.site_changes_file, self.site)
            except ConfigError as exc:
                fail(f"parameter ~site_changes_file: {exc}")
            self.site = changes.apply(self.site)
            rospy.loginfo(f"fleet_sim: site changes from {options.site_changes_file}: {changes.describe()}")
        error = initial_pose_error(fleet, self.site)
        if error:
            fail(f"bad fleet file: {error}")
        level_errors = video_level_errors(fleet)
        if level_errors:
            fail("bad fleet file: " + "; ".join(str(e) for e in level_errors))
        self.video_player = None
        if options.video_trace:
            try:
                self.video_player = VideoTracePlayer(load_video_trace(options.video_trace, fleet))
            except VideoTraceError as exc:
                fail(f"parameter ~video_trace: {exc}")
        if options.sensor_workers > 0:
            # Robots' kinematics here; rendering and ray casting in worker processes.
            self.pool = SensorWorkerPool(fleet, self.site, options.renderer, options.sensor_workers)
            self.sim = FleetSimulation(fleet, site=self.site, renderer=None)
            self.renderer = self.pool.renderer
        else:
            self.pool = None
            self.sim = FleetSimulation(fleet, site=self.site, renderer=options.renderer)
            self.renderer = self.sim.renderer
        if options.renderer in ("fast", "egl") and self.renderer != options.renderer:  # 'auto' may pick tiny
            rospy.logwarn(
                f"renderer '{options.renderer}' unavailable (the sensor workers' log says why); "
                f"using '{self.renderer}' (slower)"
            )
        self.capture_ms = {name: 0.0 for name in self.sim.robots}
        self.lock = threading.Lock()
        self.pubs = {}
        self.videos = {}  # scheduler key -> RobotVideo, per camera robot
        # Per robot: the e-stop and the command timeout hold here, where velocities are executed.
        self.gates = {}
        self.bad_commands = {}
        for name, sim in self.sim.robots.items():
            self._robot_io(name, sim)
        rospy.Subscriber(names.ESTOP, Bool, self._on_estop, queue_size=5)
        self.tf = tf2_ros.TransformBroadcaster()
        self.static_tf = tf2_ros.StaticTransformBroadcaster()
        self.diagnostics = Publisher(names.DIAGNOSTICS, DiagnosticArray, queue_size=5)
        now = time.time()
        self.static_tf.sendTransform(self._static_transforms(now))
        rates = {n: s.rate_hz for n, s in self.sim.robots.items()}
        video_rates = {key: video.rate_hz for key, video in self.videos.items()}
        # Recorded videos: scheduled and played on their own thread (_play_recorded_video).
        self.video_lock, self.video_stop = threading.Lock(), threading.Event()
        self.video_scheduler = SensorScheduler(video_rates, now) if self.video_player and video_rates else None
        if self.video_scheduler is None:
            rates.update(video_rates)
        self.scheduler = SensorScheduler(rates, now)
        self.physics_meter = RateMeter()
        self.step_timer = StepTimer()
        # How far behind its stamp the physics was when each capture was asked for, since the start:
        # the skew between a cloud's stamp and its pose that _state_for_capture removes.
        self.capture_lag = StepTimer()
        self.physics = PhysicsClock(now, options.max_physics_step_s, options.max_catch_up_s)
        rospy.loginfo(
            "fleet_sim: %s profile, renderer %s, %d sensor worker process(es), robots %s; video: %s",
            fleet.profile.name,
            self.renderer,
            options.sensor_workers,
            ", ".join(self.sim.robots),
            self.video_player.trace.describe()
            if self.video_player
            else "rendered live at the allocated level and rate",
        )

    def _robot_io(self, name, sim):
        def topic(relative):
            return names.robot_topic(name, relative)

        pubs = {
            "points": Publisher(topic(sim.config.cloud_topic), PointCloud2, queue_size=2),
            "odom": Publisher(topic(names.ODOM), Odometry, queue_size=10),
            "joint_states": Publisher(topic(names.JOINT_STATES), JointState, queue_size=10),
            "battery": Publisher(topic(names.BATTERY), BatteryState, queue_size=2),
        }
        if sim.config.has_depth_camera:
            pubs["image"] = Publisher(topic(names.CAMERA_IMAGE), Image, queue_size=2)
            pubs["info"] = Publisher(topic(names.CAMERA_INFO), CameraInfo, queue_size=2)
            video = RobotVideo(
                name, sim.sensor_frame, self.fleet.streams, self._on_video_rate, unmanaged=self.options.video_unmanaged
            )
            self.videos[video.key] = video
        self.pubs[name] = pubs
        self.gates[name] = CommandGate(CMD_TIMEOUT_S)
        self.bad_commands[name] = 0
        rospy.Subscriber(topic(names.CMD_VEL), TwistMsg, self._on_cmd_vel, callback_args=name, queue_size=5)
        if sim.robot.is_aerial:
            rospy.Subscriber(
                topic(names.FLIGHT_COMMAND), String, self._on_flight_command, callback_args=name, queue_size=5
            )

    def _on_video_rate(self, key, rate_hz):
        if getattr(self, "video_scheduler", None) is not None:
            with self.video_lock:
                self.video_scheduler.set_rate(key, rate_hz, time.time())
            return
        with self.lock:
            scheduler = getattr(self, "scheduler", None)
            if scheduler is not None:
                scheduler.set_rate(key, rate_hz, time.time())

    def _static_transforms(self, now):
        """map -> <r>/odom (the known initial pose: only this node computes it) and the sensor mounts."""
        statics = []
        for name, sim in self.sim.robots.items():
            statics.append(
                messages.transform_stamped(sim.robot.odom_in_map(), names.MAP_FRAME, names.odom_frame(name), now)
            )
            statics.append(
                messages.transform_stamped(sim.robot.sensor_in_base(), names.base_frame(name), sim.sensor_frame, now)
            )
        return statics

    # Commands --------------------------------------------------------------------------------
    def _on_cmd_vel(self, msg, name):
        sim = self.sim.robots[name]
        twist = twist_from_msg(msg)
        reason = validate_twist(twist, sim.robot.spec.limits)
        with self.lock:
            if reason:
                self.bad_commands[name] += 1
                self.gates[name].hold()
                sim.robot.set_command(Twist())
                rospy.logwarn_throttle(
                    2.0,
                    f"{names.absolute(names.robot_topic(name, names.CMD_VEL))}: dropped {reason}; holding "
                    f"({self.bad_commands[name]} dropped so far)",
                )
                return
            self.gates[name].on_command(twist)
            sim.robot.set_command(self.gates[name].command())

    def _on_estop(self, msg):
        with self.lock:
            first = any(gate.estop is None for gate in self.gates.values())
            for name, gate in self.gates.items():
                gate.set_estop(msg.data)
                self.sim.robots[name].robot.set_command(gate.command())
        if first:
            rospy.loginfo("fleet_sim: e-stop state heard (%s)", "on" if msg.data else "off")

    def _on_flight_command(self, msg, name):
        command = msg.data.strip().lower()
        with self.lock:
            if not self.sim.robots[name].robot.flight_command(command):
                rospy.logwarn_throttle(
                    2.0,
                    f"{names.absolute(names.robot_topic(name, names.FLIGHT_COMMAND))}: unknown command '{msg.data}' (known: takeoff, land)",
                )

    # Loop ------------------------------------------------------------------------------------
    def _advance_physics(self, now, exact):
        """Integrate up to `now` when the state is about to be published (`exact`), otherwise only
        once a whole step is due: the loop wakes far more often (each finished capture) than the
        kinematics need, and each pass would step every robot."""
        with self.lock:
            steps = self.physics.steps(now, 0.0 if exact else self.options.max_physics_step_s)
            if not steps:
                return
            for name, sim in self.sim.robots.items():
                sim.robot.set_command(self.gates[name].command())
            for dt_s in steps:
                self.sim.step(dt_s)
        self.physics_meter.tick(now)

    def _publish_state(self, now, joints, battery):
        transforms = []
        for name, sim in self.sim.robots.items():
            robot = sim.robot
            base_in_odom = robot.base_in_odom()
            self.pubs[name]["odom"].publish(messages.odometry(robot, now, base_in_odom))
            transforms.append(
                messages.transform_stamped(base_in_odom, names.odom_frame(name), names.base_frame(name), now)
            )
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
        video = self.videos.get(name)
        if video is not None:
            stamp = time.time()
            task = video.wanted()
            if task is not None:
                with self.lock:
                    frame = self.sim.capture_video(task)
                video.publish(frame, stamp, time.time())
            self.scheduler.done(name, stamp, time.time())
            return
        sim = self.sim.robots[name]
        stamp, _ = self._state_for_capture(cloud_of=name)
        with self.lock:
            sensor_pose = sim.robot.sensor_in_map()
        frame = sim.sensor.capture(sensor_pose)
        self._record_capture_ms(name, 1000.0 * (time.time() - stamp))
        self._publish_frame(name, frame, stamp)
        self.scheduler.done(name, stamp, time.time())

    def _busy_sensors(self):
        return [w.busy_with for w in self.pool.workers if w.busy_with]

    def _play_recorded_video(self):
        """The recorded videos' loop, on a thread of its own: fetching a frame costs ~nothing, but
        on the main loop it would wait behind the clouds' publication (tens of ms each at 640x480)
        and fall short of its rate."""
        while not self.video_stop.is_set():
            with self.video_lock:
                now = time.time()
                for key, video in self.videos.items():
                    if self.video_scheduler.due[key] <= now:
                        task = video.wanted()
                        if task is not None:
                            video.publish(self.video_player.frame(task), now, time.time())
                        self.video_scheduler.done(key, now, time.time())
                due = self.video_scheduler.next()[1]
            # Woken at least every VIDEO_POLL_S: a faster rate set meanwhile takes effect.
            self.video_stop.wait(min(max(due - time.time(), 0.0), VIDEO_POLL_S))

    def _state_for_capture(self, cloud_of=None):
        """(stamp, the robots' poses at that wall time): the physics brought up to the stamp first,
        so that a cloud's stamp is the time of the pose it is rendered from. Before, the poses were
        the physics' as of the loop's start (up to a step behind) and the stamp was taken after the
        loop had published the finished captures: under load a cloud was stamped up to hundreds of
        ms after its pose, and the twin placed it where the robot was that much later (a turning
        robot's clouds rotated, issue 39's false change at tank_3).

        For a cloud (`cloud_of`: its robot), that robot's pose at the stamp is also published on
        /tf, as lidar odometry publishes a pose at each scan's stamp: the twin reads the pose at the
        stamp exactly, not interpolated between odometry samples. After a stall of the loop (the
        physics brought up by up to hundreds of ms at once) the samples on either side of a capture
        could lie 0.3 s apart while the robot's turn accelerated between them: the interpolated
        pose was a few degrees off, and the clouds' rays carved voxels inside closed tanks (CI on
        1d27b42, the reference mission's map)."""
        stamp = time.time()
        self.capture_lag.add(max(0.0, stamp - (self.physics.wall_start_s + self.physics.sim_time_s)))
        self._advance_physics(stamp, exact=True)
        with self.lock:
            poses = self.sim.poses()
            base_in_odom = self.sim.robots[cloud_of].robot.base_in_odom() if cloud_of is not None else None
        if base_in_odom is not None:
            self.tf.sendTransform(
                [
                    messages.transform_stamped(
                        base_in_odom, names.odom_frame(cloud_of), names.base_frame(cloud_of), stamp
                    )
                ]
            )
        return stamp, poses

    def _service_workers(self, now):
        """Publish finished captures and hand due sensors to idle workers; True if any work was done."""
        worked = False
        for name, frame, requested, started, finished in self.pool.results():
            if name in self.videos:
                self.videos[name].publish(frame, requested, time.time())
            else:
                self._record_capture_ms(name, 1000.0 * (finished - started))
                self._publish_frame(name, frame, requested)
            self.scheduler.done(name, requested, time.time())
            worked = True
        while True:
            worker = self.pool.idle_worker()
            if worker is None:
                break
            name, due = self.scheduler.next(exclude=self._busy_sensors())
            if name is None or due > now:
                break
            task = None
            if name in self.videos:
                task = self.videos[name].wanted()
                if task is None:  # nobody watches: render nothing
                    self.scheduler.done(name, now, now)
                    worked = True
                    continue
            stamp, poses = self._state_for_capture(cloud_of=None if name in self.videos else name)
            self.pool.request(worker, name, poses, stamp, task=task)
            worked = True
        return worked

    def _publish_diagnostics(self, now):
        array = DiagnosticArray()
        array.header.stamp = messages.stamp(now)
        wall = now - self._diag_wall_start
        sim_time_s = self.physics.sim_time_s
        rtf = (sim_time_s - self._diag_sim_start) / wall if wall > 0 else 1.0
        self._diag_wall_start, self._diag_sim_start = now, sim_time_s
        fleet_status = DiagnosticStatus(
            level=DiagnosticStatus.OK if rtf > 0.9 else DiagnosticStatus.WARN,
            name="cps_sim: fleet",
            hardware_id="fleet_sim",
            message=f"real-time factor {rtf:.2f}",
        )
        fleet_status.values = [
            KeyValue("real_time_factor", f"{rtf:.3f}"),
            KeyValue("profile", self.fleet.profile.name),
            KeyValue("renderer", str(self.renderer)),
            KeyValue("sensor_workers", str(len(self.pool.workers) if self.pool else 0)),
            KeyValue("physics_loop_hz", f"{self.physics_meter.rate_hz(now):.1f}"),
            KeyValue("step_ms_mean", f"{self.step_timer.mean_ms:.2f}"),
            KeyValue("step_ms_max", f"{self.step_timer.max_ms:.1f}"),
            KeyValue("capture_pose_lag_ms_mean", f"{self.capture_lag.mean_ms:.1f}"),
            KeyValue("capture_pose_lag_ms_max", f"{self.capture_lag.max_ms:.1f}"),
        ]
        self.step_timer.reset()
        array.status.append(fleet_status)
        summary = []
        for name, sim in self.sim.robots.items():
            achieved = self.scheduler.achieved_hz(name, now)
            ok = achieved >= 0.9 * sim.rate_hz
            kind = "lidar" if sim.config.has_lidar else "depth_camera"
            status = DiagnosticStatus(
                level=DiagnosticStatus.OK if ok else DiagnosticStatus.WARN,
                name=f"cps_sim: {name} {kind}",
                hardware_id=name,
                message=f"{achieved:.1f} of {sim.rate_hz:.1f} Hz",
            )
            status.values = [
                KeyValue("configured_hz", f"{sim.rate_hz:.2f}"),
                KeyValue("achieved_hz", f"{achieved:.2f}"),
                KeyValue("capture_ms", f"{self.capture_ms[name]:.1f}"),
                KeyValue("skipped_captures", str(self.scheduler.skipped[name])),
                KeyValue("dropped_commands", str(self.bad_commands[name])),
                KeyValue("battery_percentage", f"{100 * sim.robot.battery_fraction:.1f}"),
            ]
            array.status.append(status)
            summary.append(f"{name} {achieved:.1f}/{sim.rate_hz:.1f} Hz")
        self.diagnostics.publish(array)
        for video in self.videos.values():
            video.publish_status(now)
        rospy.loginfo_throttle(
            10.0,
            f"fleet_sim: achieved sensor rates {', '.join(summary)}; real-time factor {rtf:.2f}; physics brought "
            f"up to each capture's stamp by {self.capture_lag.mean_ms:.1f} ms on average, at most "
            f"{self.capture_lag.max_ms:.1f} ms, over {self.capture_lag.count} captures",
        )

    def step(self, now):
        """One pass of the loop at wall time `now`; the time it next has work, or None for at once."""
        started = time.perf_counter()
        try:
            return self._step(now)
        finally:
            self.step_timer.add(time.perf_counter() - started)

    def _capture_due(self, now):
        if self.pool is not None:
            if self.pool.idle_worker() is None:
                return False
            return self.scheduler.next(exclude=self._busy_sensors())[1] <= now
        return self.scheduler.next()[1] <= now

    def _step(self, now):
        self._advance_physics(now, exact=self.odom_task.due(now) or self._capture_due(now))
        if self.odom_task.due(now):
            joints, battery = self.joint_task.due(now), self.battery_task.due(now)
            self._publish_state(now, joints, battery)
            self.odom_task.done(now)
            if joints:
                self.joint_task.done(now)
            if battery:
                self.battery_task.done(now)
        if self.diag_task.due(now):
            self._publish_diagnostics(now)
            self.diag_task.done(now)
        if self.pool is not None:
            if self._service_workers(now):
                return None
            self.pool.check_alive()
            _, due = self.scheduler.next(exclude=self._busy_sensors())
            if self.pool.idle_worker() is None:
                due = math.inf
        else:
            name, due = self.scheduler.next()
            if name is not None and due <= now:
                self._capture_in_process(name)
                return None
        return min(due, self.odom_task.next_s, self.diag_task.next_s)

    def _idle(self, delay_s):
        """Sleep, waking early when a sensor worker finishes."""
        busy = [w.conn for w in self.pool.workers if w.busy_with] if self.pool is not None else []
        if busy:
            multiprocessing.connection.wait(busy, timeout=delay_s)
        else:
            time.sleep(delay_s)

    def spin(self):
        options = self.options
        now = time.time()
        self.odom_task = Periodic(1.0 / options.odom_rate_hz, now)
        self.joint_task = Periodic(1.0 / options.joint_state_rate_hz, now)
        self.battery_task = Periodic(1.0 / options.battery_rate_hz, now)
        diagnostics_period_s = 1.0 / options.diagnostics_rate_hz
        self.diag_task = Periodic(diagnostics_period_s, now + diagnostics_period_s)
        self._diag_wall_start, self._diag_sim_start = now, self.physics.sim_time_s
        if self.video_scheduler is not None:
            threading.Thread(target=self._play_recorded_video, name="recorded_video", daemon=True).start()
        run_realtime(self.step, self.odom_task.period_s, time.time, self._idle, rospy.is_shutdown)

    def close(self):
        self.video_stop.set()
        if self.pool is not None:
            self.pool.close()
        self.sim.close()


def main():
    init_node("fleet_sim")
    fleet = load_fleet_param()
    node = FleetSimNode(fleet, read_options())
    try:
        node.spin()
    finally:
        node.close()
