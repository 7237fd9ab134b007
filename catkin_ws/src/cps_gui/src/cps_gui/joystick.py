"""The virtual joystick's mapping from a drag (or held keys) to a velocity command, per robot type.

Pure functions, no Qt and no rospy, so the mapping is tested on its own. A drag is the offset of
the knob from the pad's centre in screen pixels (x right, y down); the command is in the robot's
base frame (REP 103: x forward, y left, z up, yaw counter-clockwise).

Full-scale deflection is the robot type's velocity limit (fleet.yaml robot_types), the table
the simulator clamps to: the joystick never asks for more than the robot executes.
"""

import dataclasses
import math
from typing import FrozenSet

from cps_fleet.robot_types import RobotType

# A deflection below this fraction of full scale is treated as zero, so a resting finger does
# not creep the robot.
DEADZONE = 0.05


@dataclasses.dataclass(frozen=True)
class VelocityCommand:
    """A Twist's non-zero axes: m/s for the linear ones, rad/s for the yaw rate."""

    linear_x: float = 0.0
    linear_y: float = 0.0
    linear_z: float = 0.0
    angular_z: float = 0.0

    @property
    def is_zero(self):
        return not (self.linear_x or self.linear_y or self.linear_z or self.angular_z)

    @property
    def planar_speed_mps(self):
        return math.hypot(self.linear_x, self.linear_y)


ZERO = VelocityCommand()


def speed_limits(robot_type):
    """Full-scale deflection of a robot type (a cps_fleet RobotType): its VelocityLimits."""
    if not isinstance(robot_type, RobotType):
        raise TypeError(f"expected a cps_fleet RobotType (fleet.robot_types[name]), got {robot_type!r}")
    return robot_type.limits


def _shape(value):
    """Clamp to [-1, 1] and apply the dead zone, rescaling so the output is continuous."""
    if not math.isfinite(value):
        return 0.0
    value = max(-1.0, min(1.0, value))
    magnitude = abs(value)
    if magnitude < DEADZONE:
        return 0.0
    return math.copysign((magnitude - DEADZONE) / (1.0 - DEADZONE), value)


def axes_to_command(robot_type, forward, lateral, climb=0.0, strafe=False):
    """Normalized axes in [-1, 1] to a command.

    forward: +1 full ahead. lateral: +1 full to the right (the stick's x); it turns the robot,
    or strafes it when `strafe` is set and the type can strafe. climb: +1 full up (aerial only;
    ignored for the others).
    """
    limits = speed_limits(robot_type)
    forward, lateral, climb = _shape(forward), _shape(lateral), _shape(climb)
    strafing = strafe and limits.can_strafe
    return VelocityCommand(
        linear_x=forward * limits.max_forward_mps,
        # Right on the stick is -y (left is +y in the base frame) and clockwise (-yaw).
        linear_y=-lateral * limits.max_lateral_mps if strafing else 0.0,
        linear_z=climb * limits.max_vertical_mps if limits.can_climb else 0.0,
        angular_z=0.0 if strafing else -lateral * limits.max_yaw_rate_rps,
    )


def drag_to_command(robot_type, dx_px, dy_px, radius_px, climb=0.0, strafe=False):
    """A knob dragged (dx_px right, dy_px down) from the centre of a pad of `radius_px`.

    The offset is clipped to the pad's circle, so a diagonal drag never exceeds full scale on
    the vector sum.
    """
    if radius_px <= 0:
        raise ValueError(f"radius_px must be positive, got {radius_px}")
    nx, ny = clip_to_unit_circle(dx_px / radius_px, dy_px / radius_px)
    return axes_to_command(robot_type, forward=-ny, lateral=nx, climb=climb, strafe=strafe)


def clip_to_unit_circle(x, y):
    norm = math.hypot(x, y)
    if not math.isfinite(norm):
        return 0.0, 0.0
    if norm > 1.0:
        return x / norm, y / norm
    return x, y


# Keyboard layout (only while the teleoperation pane has focus): W/S ahead/back, A/D turn left/
# right, Q/E strafe left/right, R/F climb/descend. Arrow keys double W/A/S/D.
KEY_AXES = {
    "w": ("forward", 1.0),
    "up": ("forward", 1.0),
    "s": ("forward", -1.0),
    "down": ("forward", -1.0),
    "a": ("turn", -1.0),
    "left": ("turn", -1.0),
    "d": ("turn", 1.0),
    "right": ("turn", 1.0),
    "q": ("strafe", -1.0),
    "e": ("strafe", 1.0),
    "r": ("climb", 1.0),
    "f": ("climb", -1.0),
}


def keys_to_command(robot_type, pressed: FrozenSet[str]):
    """Held keys (lower-case names of KEY_AXES) to a command; opposite keys cancel out."""
    limits = speed_limits(robot_type)
    axes = {"forward": 0.0, "turn": 0.0, "strafe": 0.0, "climb": 0.0}
    for key in pressed:
        if key in KEY_AXES:
            axis, sign = KEY_AXES[key]
            axes[axis] += sign
    turn = axes_to_command(robot_type, axes["forward"], axes["turn"], axes["climb"])
    if axes["strafe"] and limits.can_strafe:
        strafe = axes_to_command(robot_type, 0.0, axes["strafe"], strafe=True)
        return dataclasses.replace(turn, linear_y=strafe.linear_y)
    return turn
