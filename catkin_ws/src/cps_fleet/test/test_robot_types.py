"""The robot types' limits table: one entry per fleet robot type, physically sensible values."""
import pytest

from cps_fleet.fleet import ROBOT_TYPES
from cps_fleet.robot_types import VELOCITY_LIMITS, velocity_limits


def test_every_fleet_robot_type_has_limits():
    assert set(VELOCITY_LIMITS) == set(ROBOT_TYPES)


@pytest.mark.parametrize("robot_type", sorted(VELOCITY_LIMITS))
def test_limits_are_non_negative_and_every_type_drives_and_turns(robot_type):
    limits = velocity_limits(robot_type)
    assert limits.max_forward_mps > 0 and limits.max_yaw_rate_rps > 0
    assert limits.max_linear_accel_mps2 > 0 and limits.max_yaw_accel_rps2 > 0
    assert limits.max_lateral_mps >= 0 and limits.max_vertical_mps >= 0


def test_only_the_quadrotor_climbs():
    assert [t for t, limits in VELOCITY_LIMITS.items() if limits.can_climb] == ["aerial_depth"]


def test_unknown_type_names_the_known_ones():
    with pytest.raises(ValueError, match="wheeled_lidar"):
        velocity_limits("hexapod")
