"""Route following and the velocity mux with dead-man (pure Python, no rospy).

`RouteFollower` turns the robot's pose in `map` into a body-frame velocity toward the next
waypoint and the mission state; `VelocityMux` chooses between the route's and the operator's
commands and clamps every output to the robot type's limits.
"""

import math
import time
from typing import Callable, Optional, Tuple

from cps_fleet.config import ConfigError
from cps_fleet.site import check_waypoint
from cps_fleet.transforms import pose_matrix
from cps_sim.robots import MIN_FLIGHT_ALTITUDE_M, Twist, clamp_twist, spec_for, validate_twist

MISSION_STATES = ("idle", "transit", "inspecting", "done")
CONTROL_MODES = ("auto", "teleop")


def validate_route(route, site, robot_type):
    """Raise ConfigError (route file, waypoint line) for a waypoint outside the hall or in equipment."""
    spec_for(robot_type)
    aerial, name = robot_type.is_aerial, robot_type.name
    for waypoint, line in zip(route.waypoints, route.lines):
        if not aerial and waypoint.z != 0.0:
            raise ConfigError(
                route.path, line, f"waypoint z = {waypoint.z} m: a {name} robot drives on the floor (z = 0)"
            )
        if aerial and waypoint.z < MIN_FLIGHT_ALTITUDE_M:
            raise ConfigError(
                route.path,
                line,
                f"waypoint z = {waypoint.z} m is below the {MIN_FLIGHT_ALTITUDE_M} m minimum flight altitude",
            )
        reason = check_waypoint(site, waypoint.x, waypoint.y, waypoint.z, robot_type)
        if reason:
            raise ConfigError(route.path, line, f"waypoint rejected: {reason}")


def _wrap(angle):
    return (angle + math.pi) % (2 * math.pi) - math.pi


class RouteFollower:
    """Drives through the route's waypoints in order; aerial robots take off first and land last."""

    def __init__(self, route, robot_type, tolerance_m=0.25, heading_gain=2.0, start_xy=None):
        """`start_xy`: the robot's initial position; with it, the first update resumes at the route
        segment nearest to the robot (a restarted controller does not drive back to waypoint 0)."""
        self.route = route
        self.start_xy = start_xy
        self.spec = spec_for(robot_type)
        self.aerial = robot_type.is_aerial
        self.tolerance_m = tolerance_m
        self.heading_gain = heading_gain
        self.index = 0
        self.reached_inspect = False
        self.landing = False
        self.finished = False
        self.started = False

    @property
    def state(self):
        if not self.started:
            return "idle"
        if self.finished:
            return "done"
        if self.index >= len(self.route.waypoints):
            return "transit"  # an aerial robot landing after its last waypoint
        target = self.route.waypoints[self.index]
        return "inspecting" if self.reached_inspect and target.inspect else "transit"

    def _resume_near(self, x, y):
        points = [self.start_xy] + [(w.x, w.y) for w in self.route.waypoints]
        best, best_distance = 0, math.inf
        for i in range(len(points) - 1):
            (ax, ay), (bx, by) = points[i], points[i + 1]
            dx, dy = bx - ax, by - ay
            length2 = dx * dx + dy * dy
            f = 0.0 if length2 == 0 else max(0.0, min(1.0, ((x - ax) * dx + (y - ay) * dy) / length2))
            distance = math.hypot(ax + f * dx - x, ay + f * dy - y)
            if distance < best_distance - 1e-9:
                best, best_distance = i, distance
        self.index = best
        self.reached_inspect = any(w.inspect for w in self.route.waypoints[:best])

    def _landed_at_the_end(self, x, y, airborne):
        """An aerial robot found landed on its last waypoint, away from where it started, has flown
        its route already: a restarted controller must not take off again."""
        last = self.route.waypoints[-1]
        return (
            self.aerial
            and not airborne
            and math.hypot(last.x - x, last.y - y) <= self.tolerance_m
            and math.hypot(self.start_xy[0] - x, self.start_xy[1] - y) > self.tolerance_m
        )

    def update(self, x, y, z, yaw, airborne=None):
        """(Twist in the body frame, flight command 'takeoff'/'land' or None) for the pose in map.

        `airborne`: for aerial robots, whether it is flying (default: z above 0.5 m).
        """
        if airborne is None:
            airborne = z > 0.5
        if not self.started and self.start_xy is not None:
            self._resume_near(x, y)
            self.finished = self._landed_at_the_end(x, y, airborne)
        self.started = True
        if self.finished:
            return Twist(), None
        waypoints = self.route.waypoints
        if self.aerial and not airborne and self.index < len(waypoints) and not self.landing:
            return Twist(), "takeoff"
        while self.index < len(waypoints):
            wp = waypoints[self.index]
            close_xy = math.hypot(wp.x - x, wp.y - y) <= self.tolerance_m
            close_z = (not self.aerial) or abs(wp.z - z) <= self.tolerance_m
            if not (close_xy and close_z):
                break
            if wp.inspect:
                self.reached_inspect = True
            self.index += 1
        if self.index >= len(waypoints):
            if self.aerial:
                if airborne or z > 0.01:
                    self.landing = True
                    return Twist(), "land"
            self.finished = True
            return Twist(), None
        wp = waypoints[self.index]
        dx, dy = wp.x - x, wp.y - y
        distance = math.hypot(dx, dy)
        heading_error = _wrap(math.atan2(dy, dx) - yaw) if distance > 1e-6 else 0.0
        limits = self.spec.limits
        wz = max(-limits.max_yaw_rate_rps, min(limits.max_yaw_rate_rps, self.heading_gain * heading_error))
        speed = min(self.spec.cruise_mps, 0.8 * distance + 0.1)
        if self.aerial:
            # Fly straight at the waypoint (holonomic), turning to face the direction of travel.
            c, s = math.cos(yaw), math.sin(yaw)
            scale = speed / distance if distance > 1e-6 else 0.0
            vx, vy = (c * dx + s * dy) * scale, (-s * dx + c * dy) * scale
            vz = max(-limits.max_vertical_mps, min(limits.max_vertical_mps, 1.0 * (wp.z - z)))
            if distance < 0.5:
                wz = 0.0
            return Twist(vx, vy, vz, wz), None
        # Ground robots turn on the spot when far off heading, then drive.
        alignment = max(math.cos(heading_error), 0.0) ** 4 if abs(heading_error) < math.pi / 3 else 0.0
        return Twist(speed * alignment, 0.0, 0.0, wz), None


class RouteTracker:
    """A route controller's decisions between odometry and commands (what the node publishes).

    Idle until both the static map -> odom transform (`set_odom_in_map`) and odometry
    (`set_odom`) are known; the follower then starts from the odom frame's origin. `update`
    returns a `RouteStep`: the command to send (None once done and said so), a flight command,
    and the mission state when it changed.
    """

    def __init__(self, route, robot_type):
        self.route = route
        self.robot_type = robot_type
        self.odom_in_map = None
        self.odom_pose = None
        self.follower: Optional[RouteFollower] = None
        self.state = None  # the last state reported

    def set_odom_in_map(self, x, y, z, yaw):
        self.odom_in_map = pose_matrix(x, y, z, yaw)
        self.follower = RouteFollower(self.route, self.robot_type, start_xy=(x, y))

    def set_odom(self, x, y, z, yaw):
        self.odom_pose = pose_matrix(x, y, z, yaw)

    def pose_in_map(self):
        m = self.odom_in_map @ self.odom_pose
        return m[0, 3], m[1, 3], m[2, 3], math.atan2(m[1, 0], m[0, 0])

    def _report(self, state):
        changed = state if state != self.state else None
        self.state = state
        return changed

    def start(self):
        """The state to report before anything is known ('idle')."""
        return self._report("idle")

    def update(self) -> Tuple[Optional[Twist], Optional[str], Optional[str]]:
        """(command or None, flight command or None, new mission state or None)."""
        if self.follower is None or self.odom_pose is None:
            return None, None, None
        twist, flight = self.follower.update(*self.pose_in_map())
        command = twist if not self.follower.finished or self.state != "done" else None
        return command, flight, self._report(self.follower.state)


def is_fresh(stamp_s, now_s, timeout_s):
    """Whether a command stamped `stamp_s` still holds at `now_s`: its age lies in [0, timeout_s].

    A negative age (the clock stepped back) counts as stale, so even a non-monotonic clock can only
    stop a robot early, never keep it running.
    """
    return 0.0 <= now_s - stamp_s <= timeout_s


class VelocityMux:
    """Chooses cmd_vel from the route (auto) or the operator (teleop), with dead-man and e-stop.

    Times come from `clock` (monotonic: a step of the wall clock cannot stretch a dead-man).
    Teleop commands older than `deadman_s` and auto commands older than `auto_timeout_s` count
    as zero, and the output drops to zero at once. Until the e-stop state has been heard (a
    restarted mux does not know it) the output is zero. Non-finite or absurd commands are dropped
    (counted) and the robot holds.
    """

    def __init__(self, robot_type, deadman_s=0.5, auto_timeout_s=1.0, clock: Callable[[], float] = time.monotonic):
        self.limits = spec_for(robot_type).limits
        self.deadman_s = deadman_s
        self.auto_timeout_s = auto_timeout_s
        self.clock = clock
        self.mode = "auto"
        self.estop: Optional[bool] = None  # None: not heard yet
        self._auto: Optional[Twist] = None
        self._auto_t = -math.inf
        self._teleop: Optional[Twist] = None
        self._teleop_t = -math.inf
        self.output = Twist()
        self._output_t: Optional[float] = None
        self.dropped = 0

    def _now(self, now_s):
        return self.clock() if now_s is None else now_s

    def _accept(self, twist):
        reason = validate_twist(twist, self.limits)
        if reason:
            self.dropped += 1
        return reason

    def on_auto(self, twist, now_s=None):
        """Store a route command; returns why it was dropped, or None."""
        reason = self._accept(twist)
        if reason:
            self._auto = None  # hold: a bad command must not leave the last good one running
            return reason
        self._auto, self._auto_t = twist, self._now(now_s)
        return None

    def on_teleop(self, twist, now_s=None):
        reason = self._accept(twist)
        if reason:
            self._teleop = None
            return reason
        self._teleop, self._teleop_t = twist, self._now(now_s)
        return None

    def set_mode(self, mode):
        if mode not in CONTROL_MODES:
            raise ValueError(f"unknown control mode '{mode}' (known: {', '.join(CONTROL_MODES)})")
        self.mode = mode

    def set_estop(self, active):
        self.estop = bool(active)

    @property
    def stopped(self):
        """E-stop active or not yet heard."""
        return self.estop is not False

    def selected(self, now_s=None):
        """The raw command the mode selects now, or None when stale, stopped or missing."""
        now_s = self._now(now_s)
        if self.stopped:
            return None
        if self.mode == "teleop":
            fresh = self._teleop is not None and is_fresh(self._teleop_t, now_s, self.deadman_s)
            return self._teleop if fresh else None
        fresh = self._auto is not None and is_fresh(self._auto_t, now_s, self.auto_timeout_s)
        return self._auto if fresh else None

    def update(self, now_s=None):
        """The clamped command to execute now (velocity and acceleration limits)."""
        now_s = self._now(now_s)
        dt = 0.0 if self._output_t is None else max(now_s - self._output_t, 0.0)
        target = self.selected(now_s)
        if target is None:
            self.output = Twist()  # stopped, stale or missing: no ramp down
        else:
            self.output = clamp_twist(target, self.limits, self.output, dt)
        self._output_t = now_s
        return self.output


class CommandGate:
    """What the component that executes velocities (fleet_sim, per robot) lets through.

    The e-stop holds here too, so a publisher that bypasses the mux cannot move a stopped robot.
    Zero until the e-stop state has been heard and a command is fresh (younger than `timeout_s`
    on `clock`); a command received during an e-stop is discarded, not kept for afterwards.
    """

    def __init__(self, timeout_s=0.5, clock: Callable[[], float] = time.monotonic):
        self.timeout_s = timeout_s
        self.clock = clock
        self.estop: Optional[bool] = None
        self._command: Optional[Twist] = None
        self._command_t = -math.inf

    def set_estop(self, active):
        self.estop = bool(active)
        if self.estop:
            self._command = None

    def on_command(self, twist, now_s=None):
        if self.estop is not False:
            self._command = None
            return
        self._command, self._command_t = twist, self.clock() if now_s is None else now_s

    def hold(self):
        """Forget the command (a bad one arrived): zero until the next good one."""
        self._command = None

    def command(self, now_s=None):
        """The twist to execute now."""
        now_s = self.clock() if now_s is None else now_s
        if self.estop is not False or self._command is None or not is_fresh(self._command_t, now_s, self.timeout_s):
            return Twist()
        return self._command
