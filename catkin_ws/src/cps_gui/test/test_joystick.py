"""The joystick mapping per robot type, without Qt or ROS."""

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cps_fleet.fleet import ROBOT_TYPES, load_fleet
from cps_gui import joystick

TYPES = load_fleet().robot_types


@pytest.mark.parametrize("robot_type", ["wheeled_lidar", "wheeled_depth"])
def test_diff_drive_up_is_forward_right_is_clockwise_and_never_strafes_or_climbs(robot_type):
    limits = joystick.speed_limits(TYPES[robot_type])
    ahead = joystick.drag_to_command(TYPES[robot_type], 0, -100, 100)
    assert ahead == joystick.VelocityCommand(linear_x=limits.max_forward_mps)
    right = joystick.drag_to_command(TYPES[robot_type], 100, 0, 100, climb=1.0, strafe=True)
    assert right == joystick.VelocityCommand(angular_z=-limits.max_yaw_rate_rps)
    back_left = joystick.drag_to_command(TYPES[robot_type], -30, 40, 100)
    assert back_left.linear_x < 0 and back_left.angular_z > 0


def test_quadruped_strafes_when_asked_and_turns_otherwise():
    limits = joystick.speed_limits(TYPES["legged_depth"])
    left = joystick.drag_to_command(TYPES["legged_depth"], -100, 0, 100, strafe=True)
    assert left == joystick.VelocityCommand(linear_y=limits.max_lateral_mps)
    turn = joystick.drag_to_command(TYPES["legged_depth"], -100, 0, 100)
    assert turn == joystick.VelocityCommand(angular_z=limits.max_yaw_rate_rps)
    assert joystick.drag_to_command(TYPES["legged_depth"], 0, 0, 100, climb=1.0).is_zero


def test_quadrotor_climbs_strafes_and_turns():
    limits = joystick.speed_limits(TYPES["aerial_depth"])
    up = joystick.drag_to_command(TYPES["aerial_depth"], 0, 0, 100, climb=1.0)
    assert up == joystick.VelocityCommand(linear_z=limits.max_vertical_mps)
    down = joystick.axes_to_command(TYPES["aerial_depth"], 0, 0, climb=-0.5)
    assert down.linear_z == pytest.approx(
        -limits.max_vertical_mps * (0.5 - joystick.DEADZONE) / (1 - joystick.DEADZONE)
    )
    right = joystick.drag_to_command(TYPES["aerial_depth"], 100, 0, 100, strafe=True)
    assert right.linear_y == pytest.approx(-limits.max_lateral_mps)


def test_drag_beyond_the_pad_is_clipped_to_full_scale():
    limits = joystick.speed_limits(TYPES["wheeled_depth"])
    far = joystick.drag_to_command(TYPES["wheeled_depth"], 0, -1000, 100)
    assert far.linear_x == pytest.approx(limits.max_forward_mps)
    diagonal = joystick.drag_to_command(TYPES["wheeled_depth"], 1000, -1000, 100)
    assert diagonal.linear_x == pytest.approx(
        limits.max_forward_mps * (math.sqrt(0.5) - joystick.DEADZONE) / (1 - joystick.DEADZONE)
    )


def test_dead_zone_gives_exact_zero():
    assert joystick.drag_to_command(TYPES["wheeled_lidar"], 2, -3, 100).is_zero


def test_bad_input_is_rejected_or_neutral():
    with pytest.raises(TypeError, match="RobotType.*got 'tank'"):
        joystick.drag_to_command("tank", 0, -10, 100)
    with pytest.raises(ValueError, match="radius_px"):
        joystick.drag_to_command(TYPES["wheeled_lidar"], 0, -10, 0)
    assert joystick.drag_to_command(TYPES["wheeled_lidar"], math.nan, math.inf, 100).is_zero
    assert joystick.axes_to_command(TYPES["wheeled_lidar"], math.nan, 0.5).linear_x == 0.0


@given(
    dx=st.floats(-1e4, 1e4),
    dy=st.floats(-1e4, 1e4),
    climb=st.floats(-5, 5),
    strafe=st.booleans(),
    robot_type=st.sampled_from(sorted(ROBOT_TYPES)),
)
def test_commands_never_exceed_the_type_limits(dx, dy, climb, strafe, robot_type):
    limits = joystick.speed_limits(TYPES[robot_type])
    c = joystick.drag_to_command(TYPES[robot_type], dx, dy, 50, climb=climb, strafe=strafe)
    assert abs(c.linear_x) <= limits.max_forward_mps + 1e-9
    assert abs(c.linear_y) <= limits.max_lateral_mps + 1e-9
    assert abs(c.linear_z) <= limits.max_vertical_mps + 1e-9
    assert abs(c.angular_z) <= limits.max_yaw_rate_rps + 1e-9


def test_keys_map_like_the_stick_and_opposites_cancel():
    limits = joystick.speed_limits(TYPES["legged_depth"])
    assert joystick.keys_to_command(TYPES["legged_depth"], frozenset({"w"})).linear_x == pytest.approx(
        limits.max_forward_mps
    )
    assert joystick.keys_to_command(TYPES["legged_depth"], frozenset({"w", "s"})).is_zero
    strafe = joystick.keys_to_command(TYPES["legged_depth"], frozenset({"q", "d"}))
    assert strafe.linear_y == pytest.approx(limits.max_lateral_mps) and strafe.angular_z == pytest.approx(
        -limits.max_yaw_rate_rps
    )
    assert joystick.keys_to_command(TYPES["wheeled_lidar"], frozenset({"q", "r"})).is_zero
    assert joystick.keys_to_command(TYPES["aerial_depth"], frozenset({"r"})).linear_z > 0


@pytest.mark.parametrize("robot_type", sorted(ROBOT_TYPES))
def test_full_scale_deflection_is_what_the_simulator_executes(robot_type):
    """The GUI must neither command more than the simulated robot executes nor less than it can."""
    from cps_sim.robots import spec_for

    limits = spec_for(TYPES[robot_type]).limits
    ahead = joystick.axes_to_command(TYPES[robot_type], forward=1.0, lateral=0.0)
    turn = joystick.axes_to_command(TYPES[robot_type], forward=0.0, lateral=-1.0)
    strafe = joystick.axes_to_command(TYPES[robot_type], forward=0.0, lateral=-1.0, strafe=True)
    climb = joystick.axes_to_command(TYPES[robot_type], forward=0.0, lateral=0.0, climb=1.0)
    assert ahead.linear_x == pytest.approx(limits.max_forward_mps)
    assert turn.angular_z == pytest.approx(limits.max_yaw_rate_rps)
    assert strafe.linear_y == pytest.approx(limits.max_lateral_mps)
    assert climb.linear_z == pytest.approx(limits.max_vertical_mps)
