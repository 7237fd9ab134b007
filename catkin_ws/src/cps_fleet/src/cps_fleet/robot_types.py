"""Per robot type velocity and acceleration limits: the one table the simulator and the GUI read.

Plain data (no ROS, no numpy), keyed by the type names of cps_fleet.fleet.ROBOT_TYPES, so that a
later fleet.yaml can declare robot types with the same fields. The simulator clamps every executed
command to these limits; the operator GUI's joystick uses them as its full-scale deflection.
"""
import dataclasses


@dataclasses.dataclass(frozen=True)
class VelocityLimits:
    """What a robot type can execute, in its base frame (REP 103)."""

    max_forward_mps: float
    max_lateral_mps: float      # 0 for non-holonomic bases
    max_vertical_mps: float     # 0 for ground robots
    max_yaw_rate_rps: float
    max_linear_accel_mps2: float
    max_yaw_accel_rps2: float

    @property
    def can_strafe(self):
        return self.max_lateral_mps > 0.0

    @property
    def can_climb(self):
        return self.max_vertical_mps > 0.0


VELOCITY_LIMITS = {
    # Agilex Scout 2.0
    "wheeled_lidar": VelocityLimits(max_forward_mps=1.5, max_lateral_mps=0.0, max_vertical_mps=0.0,
                                    max_yaw_rate_rps=1.5, max_linear_accel_mps2=1.0, max_yaw_accel_rps2=2.0),
    # Clearpath Jackal
    "wheeled_depth": VelocityLimits(max_forward_mps=2.0, max_lateral_mps=0.0, max_vertical_mps=0.0,
                                    max_yaw_rate_rps=4.0, max_linear_accel_mps2=2.0, max_yaw_accel_rps2=4.0),
    # CHAMP quadruped
    "legged_depth": VelocityLimits(max_forward_mps=0.6, max_lateral_mps=0.3, max_vertical_mps=0.0,
                                   max_yaw_rate_rps=1.0, max_linear_accel_mps2=0.8, max_yaw_accel_rps2=1.5),
    # 3DR Iris quadrotor
    "aerial_depth": VelocityLimits(max_forward_mps=2.0, max_lateral_mps=2.0, max_vertical_mps=1.0,
                                   max_yaw_rate_rps=1.5, max_linear_accel_mps2=1.5, max_yaw_accel_rps2=2.0),
}


def velocity_limits(robot_type):
    """The VelocityLimits of a type; an unknown type is a ValueError naming the known ones."""
    try:
        return VELOCITY_LIMITS[robot_type]
    except KeyError:
        raise ValueError(f"unknown robot type '{robot_type}' (known: {', '.join(VELOCITY_LIMITS)})") from None
