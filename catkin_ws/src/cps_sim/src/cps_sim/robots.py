"""The simulated robots: kinematics, joints and battery, with each type's body, sensor mount and
velocity limits.

Pure numpy. Robots move kinematically (their pose is integrated from the executed velocity,
with the type's velocity and acceleration limits); odometry is that pose relative to the known
initial pose. Body box, sensor mount and limits are the fleet's (fleet.yaml robot_types, a
cps_fleet RobotType), shared with the twin; the rest (ROBOT_SPECS: model, colour, joints, route
speed, battery) is the simulator's, modelled on the default fleet's four types; a fleet's own type
gets the rest of its base and sensor kind (`spec_for`).
"""

import dataclasses
import math
from typing import Optional, Tuple

import numpy as np

from cps_fleet.fleet import ROBOT_TYPES
from cps_fleet.robot_types import RobotType, VelocityLimits
from cps_fleet.transforms import pose_matrix, rigid_inverse, sensor_in_base

# Beyond this many times a limit a command is absurd: dropped, not clamped.
ABSURD_FACTOR = 10.0


@dataclasses.dataclass(frozen=True)
class RobotSpec:
    type: str
    model: str
    rgb: Tuple[float, float, float]
    limits: Optional[VelocityLimits]  # the fleet's robot type's (spec_for), shared with the GUI's joystick
    cruise_mps: float  # the route controller's travel speed
    joint_names: Tuple[str, ...]
    wheel_radius_m: float = 0.0
    track_m: float = 0.0
    battery_capacity_wh: float = 100.0
    battery_nominal_v: float = 24.0
    idle_power_w: float = 20.0
    motion_power_w_per_mps: float = 40.0
    sensor_power_w: float = 10.0


_CHAMP_LEGS = ("lf", "rf", "lh", "rh")

ROBOT_SPECS = {
    "wheeled_lidar": RobotSpec(
        type="wheeled_lidar",
        model="Agilex Scout 2.0",
        rgb=(0.9, 0.9, 0.9),
        limits=None,
        cruise_mps=0.8,
        joint_names=("front_left_wheel", "front_right_wheel", "rear_left_wheel", "rear_right_wheel"),
        wheel_radius_m=0.165,
        track_m=0.58,
        battery_capacity_wh=720.0,
        battery_nominal_v=24.0,
        idle_power_w=60.0,
        motion_power_w_per_mps=150.0,
        sensor_power_w=12.0,
    ),
    "wheeled_depth": RobotSpec(
        type="wheeled_depth",
        model="Clearpath Jackal",
        rgb=(0.95, 0.75, 0.1),
        limits=None,
        cruise_mps=0.8,
        joint_names=("front_left_wheel", "front_right_wheel", "rear_left_wheel", "rear_right_wheel"),
        wheel_radius_m=0.098,
        track_m=0.37,
        battery_capacity_wh=270.0,
        battery_nominal_v=24.0,
        idle_power_w=30.0,
        motion_power_w_per_mps=60.0,
        sensor_power_w=5.0,
    ),
    "legged_depth": RobotSpec(
        type="legged_depth",
        model="CHAMP quadruped",
        rgb=(0.2, 0.2, 0.22),
        limits=None,
        cruise_mps=0.45,
        joint_names=tuple(f"{leg}_{j}_joint" for leg in _CHAMP_LEGS for j in ("hip", "upper_leg", "lower_leg")),
        battery_capacity_wh=150.0,
        battery_nominal_v=24.0,
        idle_power_w=40.0,
        motion_power_w_per_mps=120.0,
        sensor_power_w=5.0,
    ),
    "aerial_depth": RobotSpec(
        type="aerial_depth",
        model="3DR Iris quadrotor",
        rgb=(0.15, 0.15, 0.15),
        limits=None,
        cruise_mps=1.0,
        joint_names=("rotor_0_joint", "rotor_1_joint", "rotor_2_joint", "rotor_3_joint"),
        battery_capacity_wh=60.0,
        battery_nominal_v=11.1,
        idle_power_w=10.0,
        motion_power_w_per_mps=20.0,
        sensor_power_w=5.0,
    ),
}
assert set(ROBOT_SPECS) == set(ROBOT_TYPES)

TAKEOFF_ALTITUDE_M = 1.0
CLIMB_RATE_MPS = 0.6
MIN_FLIGHT_ALTITUDE_M = 0.3
AERIAL_HOVER_POWER_W = 150.0


# The spec a type of the fleet's own gets, by (base, sensor kind).
_SPEC_OF_KIND = {
    ("wheeled", "lidar"): "wheeled_lidar",
    ("wheeled", "depth"): "wheeled_depth",
    ("legged", "lidar"): "legged_depth",
    ("legged", "depth"): "legged_depth",
    ("aerial", "lidar"): "aerial_depth",
    ("aerial", "depth"): "aerial_depth",
}


def spec_for(rt: RobotType):
    """The RobotSpec of a robot type (a cps_fleet RobotType): the spec named like it, else the spec of
    its base and sensor kind, with the type's velocity limits."""
    if not isinstance(rt, RobotType):
        raise TypeError(f"expected a cps_fleet RobotType (fleet.robot_types[name]), got {rt!r}")
    spec = ROBOT_SPECS.get(rt.name) or ROBOT_SPECS[_SPEC_OF_KIND[(rt.base, rt.sensor)]]
    return dataclasses.replace(spec, type=rt.name, limits=rt.limits)


@dataclasses.dataclass
class Twist:
    """Velocity in the robot's body frame: vx, vy, vz (m/s), wz (rad/s)."""

    vx: float = 0.0
    vy: float = 0.0
    vz: float = 0.0
    wz: float = 0.0

    def as_array(self):
        return np.array([self.vx, self.vy, self.vz, self.wz])

    @classmethod
    def from_array(cls, a):
        return cls(float(a[0]), float(a[1]), float(a[2]), float(a[3]))


def validate_twist(twist, limits):
    """None if the command is usable, else why it must be dropped (NaN/Inf or absurdly large)."""
    values = twist.as_array()
    if not np.all(np.isfinite(values)):
        return f"non-finite velocity {values.tolist()}"
    caps = np.array(
        [
            limits.max_forward_mps,
            max(limits.max_lateral_mps, limits.max_forward_mps),
            max(limits.max_vertical_mps, limits.max_forward_mps),
            limits.max_yaw_rate_rps,
        ]
    )
    if np.any(np.abs(values) > ABSURD_FACTOR * caps):
        return f"absurd velocity {values.tolist()} (limits {caps.tolist()})"
    return None


def _clip(value, bound):
    return min(max(value, -bound), bound)


def clamp_twist(twist, limits, previous=None, dt_s=None):
    """Clamp to the velocity limits and, given the previous output and dt, the acceleration limits.

    Scalar Python, not numpy: fleet_sim calls it twice per robot per physics step (with 16
    robots, ~1600 times a second), where numpy's per-call overhead was most of the loop's time."""
    vx, vy = _clip(twist.vx, limits.max_forward_mps), _clip(twist.vy, limits.max_lateral_mps)
    vz, wz = _clip(twist.vz, limits.max_vertical_mps), _clip(twist.wz, limits.max_yaw_rate_rps)
    if previous is not None and dt_s is not None:
        linear, yaw = limits.max_linear_accel_mps2 * dt_s, limits.max_yaw_accel_rps2 * dt_s
        vx = previous.vx + _clip(vx - previous.vx, linear)
        vy = previous.vy + _clip(vy - previous.vy, linear)
        vz = previous.vz + _clip(vz - previous.vz, linear)
        wz = previous.wz + _clip(wz - previous.wz, yaw)
    return Twist(float(vx), float(vy), float(vz), float(wz))


class Robot:
    """One robot's kinematic state, joints and battery. Poses are in `map` unless named odom."""

    def __init__(self, name, robot_type, initial_pose):
        self.name = name
        self.spec = spec_for(robot_type)
        self.robot_type = robot_type
        self.type = self.robot_type.name
        self.initial = np.array([initial_pose.x, initial_pose.y, initial_pose.z, initial_pose.yaw_rad])
        self.x, self.y, self.z, self.yaw = self.initial.tolist()
        self.velocity = Twist()  # executed, body frame
        self.command = Twist()  # last accepted command
        self.joint_positions = np.zeros(len(self.spec.joint_names))
        self.joint_velocities = np.zeros(len(self.spec.joint_names))
        self.gait_phase = 0.0
        self.energy_used_wh = 0.0
        self.power_w = self.spec.idle_power_w
        self.sensing = True
        self.flight_state = "landed" if self.is_aerial else "ground"
        self.distance_m = 0.0
        # What step() executes within: the type's limits, with the climb rate for take-off and landing.
        lim = self.spec.limits
        self._motion_limits = dataclasses.replace(lim, max_vertical_mps=max(lim.max_vertical_mps, CLIMB_RATE_MPS))

    @property
    def is_aerial(self):
        return self.robot_type.is_aerial

    def set_command(self, twist):
        self.command = twist

    def flight_command(self, command):
        """'takeoff' or 'land' (aerial only); returns False if the command does not apply."""
        if not self.is_aerial or command not in ("takeoff", "land"):
            return False
        if command == "takeoff" and self.flight_state in ("landed", "landing"):
            self.flight_state = "taking_off"
        elif command == "land" and self.flight_state in ("flying", "taking_off"):
            self.flight_state = "landing"
        return True

    def step(self, dt_s):
        """Advance the robot by dt_s seconds of the executed command."""
        lim = self.spec.limits
        target = clamp_twist(self.command, lim)
        if self.is_aerial:
            if self.flight_state == "landed":
                target = Twist()
            elif self.flight_state == "taking_off":
                target = Twist(0.0, 0.0, CLIMB_RATE_MPS, 0.0)
            elif self.flight_state == "landing":
                target = Twist(0.0, 0.0, -CLIMB_RATE_MPS, 0.0)
        else:
            target.vz = 0.0
        self.velocity = clamp_twist(target, self._motion_limits, self.velocity, dt_s)
        v = self.velocity
        yaw_mid = self.yaw + 0.5 * v.wz * dt_s
        c, s = math.cos(yaw_mid), math.sin(yaw_mid)
        dx, dy = (c * v.vx - s * v.vy) * dt_s, (s * v.vx + c * v.vy) * dt_s
        self.x += dx
        self.y += dy
        self.z += v.vz * dt_s
        self.yaw = (self.yaw + v.wz * dt_s + math.pi) % (2 * math.pi) - math.pi
        self.distance_m += math.hypot(dx, dy)
        if self.is_aerial:
            self._update_flight()
        else:
            self.z = self.initial[2]
        self._update_joints(dt_s)
        self._update_battery(dt_s)

    def _update_flight(self):
        if self.flight_state == "taking_off" and self.z >= TAKEOFF_ALTITUDE_M:
            self.flight_state = "flying"
        if self.flight_state == "flying" and self.z < MIN_FLIGHT_ALTITUDE_M:
            self.z = MIN_FLIGHT_ALTITUDE_M
            self.velocity.vz = max(self.velocity.vz, 0.0)
        if self.z <= 0.0:
            self.z = 0.0
            if self.flight_state == "landing":
                self.flight_state = "landed"
                self.velocity = Twist()

    def _update_joints(self, dt_s):
        v = self.velocity
        spec = self.spec
        if spec.wheel_radius_m > 0:
            left = (v.vx - v.wz * spec.track_m / 2) / spec.wheel_radius_m
            right = (v.vx + v.wz * spec.track_m / 2) / spec.wheel_radius_m
            self.joint_velocities = np.array([left, right, left, right])
            self.joint_positions = (self.joint_positions + self.joint_velocities * dt_s + math.pi) % (
                2 * math.pi
            ) - math.pi
        elif self.robot_type.base == "legged":
            self.joint_positions, self.joint_velocities = self._trot(dt_s)
        else:
            spin = 0.0 if self.flight_state == "landed" else 900.0
            self.joint_velocities = np.array([spin, -spin, spin, -spin])
            self.joint_positions = (self.joint_positions + self.joint_velocities * dt_s + math.pi) % (
                2 * math.pi
            ) - math.pi

    def _trot(self, dt_s):
        """A trot: diagonal leg pairs swing in antiphase, stride scaled by the body speed."""
        v = self.velocity
        speed = math.hypot(v.vx, v.vy) + 0.2 * abs(v.wz)
        amplitude = min(speed / max(self.spec.limits.max_forward_mps, 1e-6), 1.0)
        self.gait_phase = (self.gait_phase + 2 * math.pi * 2.0 * dt_s * (1.0 if amplitude > 0.01 else 0.0)) % (
            2 * math.pi
        )
        positions = []
        for i, leg in enumerate(_CHAMP_LEGS):
            phase = self.gait_phase + (0.0 if leg in ("lf", "rh") else math.pi)
            hip = 0.05 * amplitude * math.sin(phase) * (1 if i % 2 == 0 else -1)
            upper = 0.6 + 0.35 * amplitude * math.sin(phase)
            lower = -1.2 - 0.4 * amplitude * max(math.cos(phase), 0.0)
            positions.extend([hip, upper, lower])
        positions = np.array(positions)
        velocities = (positions - self.joint_positions) / dt_s if dt_s > 0 else np.zeros_like(positions)
        return positions, velocities

    def _update_battery(self, dt_s):
        spec = self.spec
        v = self.velocity
        motion = math.hypot(v.vx, v.vy) + abs(v.vz) + 0.3 * abs(v.wz)
        power = (
            spec.idle_power_w + spec.motion_power_w_per_mps * motion + (spec.sensor_power_w if self.sensing else 0.0)
        )
        if self.is_aerial and self.flight_state != "landed":
            power += AERIAL_HOVER_POWER_W
        self.power_w = power
        self.energy_used_wh = min(self.energy_used_wh + power * dt_s / 3600.0, spec.battery_capacity_wh)

    @property
    def battery_fraction(self):
        return 1.0 - self.energy_used_wh / self.spec.battery_capacity_wh

    @property
    def battery_voltage_v(self):
        """Open-circuit voltage of a Li-ion pack falling from 1.17x to 0.9x nominal."""
        return self.spec.battery_nominal_v * (0.9 + 0.27 * self.battery_fraction)

    @property
    def battery_current_a(self):
        """Discharge current, negative (sensor_msgs/BatteryState: negative while discharging)."""
        return -self.power_w / self.battery_voltage_v

    # Poses -----------------------------------------------------------------------------------
    def base_in_map(self):
        return pose_matrix(self.x, self.y, self.z, self.yaw)

    def odom_in_map(self):
        """The static map -> <r>/odom transform: the known initial pose."""
        x, y, z, yaw = self.initial
        return pose_matrix(x, y, z, yaw)

    def base_in_odom(self):
        return rigid_inverse(self.odom_in_map()) @ self.base_in_map()

    def sensor_in_base(self):
        """The static mount base_link -> <r>/lidar or <r>/camera_depth_optical_frame (the type's)."""
        return sensor_in_base(self.robot_type)

    def sensor_in_map(self):
        return self.base_in_map() @ self.sensor_in_base()

    def set_pose(self, x, y, z, yaw):
        """Place the robot (tests and sample renders); odometry keeps its initial pose."""
        self.x, self.y, self.z, self.yaw = float(x), float(y), float(z), float(yaw)
        if self.is_aerial and z > 0:
            self.flight_state = "flying"
