"""Robot types as data: fleet.yaml's `robot_types:` block, read by `read_robot_types`.

A type names what its robots sense (sensor kind, cloud topic, sensor frame, map max range), how
fast they may move (VelocityLimits: the simulator clamps every executed command to them, the
operator GUI's joystick uses them as full scale), and their body box and sensor mount (Body,
SensorMount: the simulator builds and mounts them, the twin keeps the bodies out of its map and of
change detection). A real robot is a new entry in fleet.yaml, not new code. Plain data, no ROS.
"""

import dataclasses
import math
from typing import Dict, Tuple

SENSOR_KINDS = ("lidar", "depth")
BASES = ("wheeled", "legged", "aerial")
_LIMIT_KEYS = (
    "max_forward_mps",
    "max_lateral_mps",
    "max_vertical_mps",
    "max_yaw_rate_rps",
    "max_linear_accel_mps2",
    "max_yaw_accel_rps2",
)


@dataclasses.dataclass(frozen=True)
class VelocityLimits:
    """What a robot type can execute, in its base frame (REP 103)."""

    max_forward_mps: float
    max_lateral_mps: float  # 0 for non-holonomic bases
    max_vertical_mps: float  # 0 for ground robots
    max_yaw_rate_rps: float
    max_linear_accel_mps2: float
    max_yaw_accel_rps2: float

    @property
    def can_strafe(self):
        return self.max_lateral_mps > 0.0

    @property
    def can_climb(self):
        return self.max_vertical_mps > 0.0


@dataclasses.dataclass(frozen=True)
class Body:
    """A robot's body as a box, upright in base_link (REP 103: x forward, z up)."""

    half_extents_m: Tuple[float, float, float]
    center_z_m: float  # the box's centre above base_link


@dataclasses.dataclass(frozen=True)
class SensorMount:
    """Where the sensor sits in base_link (a depth camera's optical frame is turned from it)."""

    xyz_m: Tuple[float, float, float]
    pitch_deg: float  # positive looks down


@dataclasses.dataclass(frozen=True)
class RobotType:
    """One entry of fleet.yaml's robot_types."""

    name: str
    base: str  # wheeled | legged | aerial: how it moves (and the body the simulator gives it)
    sensor: str  # lidar | depth: what the simulator can simulate
    cloud_topic: str  # relative to /<robot>
    sensor_frame: str  # relative to the robot's tf prefix: <robot>/<sensor_frame>
    max_range_m: float  # the map server inserts points up to this far from the sensor
    limits: VelocityLimits
    body: Body
    sensor_mount: SensorMount

    @property
    def is_aerial(self):
        return self.base == "aerial"


def _three_numbers(reader, key, positive=False):
    value = reader.get(key, list)
    if len(value) != 3 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and (v > 0 or not positive)
        for v in value
    ):
        raise reader.error(
            key, f"must be three {'positive' if positive else 'finite'} numbers (x, y, z), got {value!r}"
        )
    return tuple(float(v) for v in value)


def _body(reader):
    reader.known_keys("half_extents_m", "center_z_m")
    return Body(
        half_extents_m=_three_numbers(reader, "half_extents_m", positive=True), center_z_m=reader.number("center_z_m")
    )


def _sensor_mount(reader):
    reader.known_keys("xyz_m", "pitch_deg")
    return SensorMount(
        xyz_m=_three_numbers(reader, "xyz_m"), pitch_deg=reader.number("pitch_deg", low=-90.0, high=90.0)
    )


def read_robot_types(reader) -> Dict[str, RobotType]:
    """{name: RobotType} from a cps_fleet.config.Reader over the robot_types mapping (ConfigError
    with file:line for a missing or bad key)."""
    types = {}
    for name in reader.value:
        entry = reader.child(name).known_keys(
            "base", "sensor", "cloud_topic", "sensor_frame", "max_range_m", "limits", "body", "sensor_mount"
        )
        base, sensor = entry.get("base", str), entry.get("sensor", str)
        if base not in BASES:
            raise entry.error("base", f"unknown base '{base}' (known: {', '.join(BASES)})")
        if sensor not in SENSOR_KINDS:
            raise entry.error("sensor", f"unknown sensor kind '{sensor}' (known: {', '.join(SENSOR_KINDS)})")
        limits = entry.child("limits").known_keys(*_LIMIT_KEYS)
        for key in ("cloud_topic", "sensor_frame"):
            if entry.get(key, str).startswith("/"):
                raise entry.error(key, "must be relative (it is resolved under the robot's name)")
        types[name] = RobotType(
            name=name,
            base=base,
            sensor=sensor,
            cloud_topic=entry.get("cloud_topic", str),
            sensor_frame=entry.get("sensor_frame", str),
            max_range_m=entry.number("max_range_m", low=0.0, low_open=True),
            limits=VelocityLimits(**{key: limits.number(key, low=0.0) for key in _LIMIT_KEYS}),
            body=_body(entry.child("body")),
            sensor_mount=_sensor_mount(entry.child("sensor_mount")),
        )
        for key in ("max_forward_mps", "max_yaw_rate_rps", "max_linear_accel_mps2", "max_yaw_accel_rps2"):
            if getattr(types[name].limits, key) <= 0.0:
                raise limits.error(key, "must be positive: every robot drives and turns")
    if not types:
        raise reader.error(None, "no robot types")
    return types
