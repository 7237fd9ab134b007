"""Route following, the velocity mux (dead-man, modes, e-stop, limits) and bad commands, without ROS."""

import math

import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import load_fleet, load_route
from cps_fleet.site import load_site
from cps_sim.controllers import RouteFollower, VelocityMux, validate_route
from cps_sim.robots import Robot, Twist, spec_for

TYPES = load_fleet().robot_types


def _fly(robot_cfg, route, seconds=400.0, dt=0.05):
    robot = Robot(robot_cfg.name, robot_cfg.robot_type, robot_cfg.initial_pose)
    follower, mux = RouteFollower(route, robot_cfg.robot_type), VelocityMux(robot_cfg.robot_type)
    mux.set_estop(False)
    states, t = [], 0.0
    while t < seconds and follower.state != "done":
        twist, flight = follower.update(robot.x, robot.y, robot.z, robot.yaw)
        if flight:
            robot.flight_command(flight)
        mux.on_auto(twist, t)
        robot.set_command(mux.update(t))
        robot.step(dt)
        t += dt
        if not states or states[-1] != follower.state:
            states.append(follower.state)
    return robot, states, t


@pytest.mark.parametrize("name", ["scout", "jackal", "champ", "iris"])
def test_each_default_route_is_valid_and_ends_done_within_four_minutes(name):
    fleet = load_fleet(profile="light")
    cfg = fleet.robot(name)
    route = fleet.route(name)
    site = load_site(fleet.site_path)
    validate_route(route, site, cfg.robot_type)
    robot, states, t = _fly(cfg, route)
    assert states[0] == "transit" and "inspecting" in states and states[-1] == "done", states
    assert t < 240.0
    last = route.waypoints[-1]
    assert math.hypot(robot.x - last.x, robot.y - last.y) < 0.5
    if cfg.type == "aerial_depth":
        assert robot.flight_state == "landed" and robot.z == 0.0


def test_route_through_equipment_is_rejected_with_file_and_line(tmp_path):
    site = load_site(load_fleet().site_path)
    tank = site.item("tank_1")
    path = tmp_path / "route.yaml"
    path.write_text(f"waypoints:\n  - {{x: -8.5, y: -4.0}}\n  - {{x: {tank.x}, y: {tank.y}, inspect: true}}\n")
    with pytest.raises(ConfigError) as err:
        validate_route(load_route(path), site, TYPES["wheeled_lidar"])
    assert f"{path}:3:" in str(err.value) and "tank_1" in str(err.value)
    path.write_text("waypoints:\n  - {x: 30.0, y: 0.0}\n")
    with pytest.raises(ConfigError, match="outside the hall"):
        validate_route(load_route(path), site, TYPES["wheeled_lidar"])


def test_a_type_name_in_place_of_a_robot_type_is_a_clear_error():
    with pytest.raises(TypeError, match="RobotType.*got 'submarine'"):
        spec_for("submarine")


def test_deadman_stops_teleop_and_auto_takes_back_over():
    mux = VelocityMux(TYPES["wheeled_depth"])
    mux.set_estop(False)
    mux.set_mode("teleop")
    mux.on_teleop(Twist(vx=0.5), 0.0)
    for k in range(1, 5):
        out = mux.update(0.1 * k)
    assert out.vx == pytest.approx(0.5)
    t = 0.4
    while t < 0.6:  # no teleop command since t = 0 -> dead-man at 0.5 s
        t += 0.05
        out = mux.update(t)
    assert out.vx == 0.0  # a dead-man stops at once, no ramp down
    for _ in range(10):
        t += 0.05
        out = mux.update(t)
    assert out.vx == 0.0
    mux.on_auto(Twist(vx=0.3), t)
    assert mux.update(t + 0.05).vx == 0.0  # still teleop: auto ignored
    mux.set_mode("auto")
    for _ in range(10):
        t += 0.05
        mux.on_auto(Twist(vx=0.3), t)
        out = mux.update(t)
    assert out.vx == pytest.approx(0.3)


def test_estop_zeroes_at_once():
    mux = VelocityMux(TYPES["wheeled_lidar"])
    mux.set_estop(False)
    mux.on_auto(Twist(vx=1.0), 0.0)
    for k in range(20):
        mux.update(0.1 * k)
    mux.set_estop(True)
    assert mux.update(2.0).vx == 0.0
    with pytest.raises(ValueError, match="known: auto, teleop"):
        mux.set_mode("manual")


@pytest.mark.parametrize("bad", [Twist(vx=float("nan")), Twist(wz=float("inf")), Twist(vx=1e6)])
def test_nan_inf_and_absurd_commands_are_dropped_and_the_robot_holds(bad):
    mux = VelocityMux(TYPES["wheeled_depth"])
    mux.set_estop(False)
    mux.on_auto(Twist(vx=0.5), 0.0)
    for k in range(1, 10):
        mux.update(0.05 * k)
    reason = mux.on_auto(bad, 0.5)
    assert reason and mux.dropped == 1
    out = mux.update(0.55)
    assert math.isfinite(out.vx) and out.vx < 0.5  # holding: decelerating to zero
    for k in range(12, 40):
        out = mux.update(0.05 * k)
    assert out.vx == 0.0


def test_limits_clamp_velocity_and_acceleration():
    limits = spec_for(TYPES["legged_depth"]).limits
    mux = VelocityMux(TYPES["legged_depth"])
    mux.set_estop(False)
    mux.on_auto(Twist(vx=5.0, vy=5.0, wz=-9.0), 0.0)
    first = mux.update(0.0)
    second = mux.update(0.1)
    assert second.vx == pytest.approx(min(limits.max_linear_accel_mps2 * 0.1, limits.max_forward_mps))
    for k in range(2, 60):
        mux.on_auto(Twist(vx=5.0, vy=5.0, wz=-9.0), 0.1 * k)
        out = mux.update(0.1 * k)
    assert out.vx == pytest.approx(limits.max_forward_mps) and out.vy == pytest.approx(limits.max_lateral_mps)
    assert out.wz == pytest.approx(-limits.max_yaw_rate_rps)
    assert first.vx == 0.0


def test_battery_drains_faster_when_moving_and_joints_move():
    fleet = load_fleet()
    still = Robot("a", TYPES["legged_depth"], fleet.robot("champ").initial_pose)
    moving = Robot("b", TYPES["legged_depth"], fleet.robot("champ").initial_pose)
    moving.set_command(Twist(vx=0.5))
    for _ in range(200):
        still.step(0.05)
        moving.step(0.05)
    assert moving.battery_fraction < still.battery_fraction < 1.0
    assert moving.battery_current_a < still.battery_current_a < 0.0
    assert len(moving.spec.joint_names) == 12 and any(
        abs(p - q) > 0.05 for p, q in zip(moving.joint_positions, still.joint_positions)
    )


def test_quadrotor_takes_off_holds_altitude_and_lands():
    fleet = load_fleet()
    iris = Robot("iris", TYPES["aerial_depth"], fleet.robot("iris").initial_pose)
    iris.set_command(Twist(vx=1.0))
    iris.step(0.1)
    assert iris.x == fleet.robot("iris").initial_pose.x  # landed: ignores cmd_vel
    iris.flight_command("takeoff")
    for _ in range(100):
        iris.step(0.05)
    assert iris.flight_state == "flying"
    z = iris.z
    iris.set_command(Twist())
    for _ in range(40):
        iris.step(0.05)
    assert iris.z == pytest.approx(z, abs=0.05)  # altitude hold
    iris.flight_command("land")
    for _ in range(200):
        iris.step(0.05)
    assert iris.flight_state == "landed" and iris.z == 0.0


def test_a_restarted_route_controller_resumes_where_the_robot_is():
    fleet = load_fleet()
    cfg = fleet.robot("scout")
    route = fleet.route("scout")
    start = (cfg.initial_pose.x, cfg.initial_pose.y)
    fresh = RouteFollower(route, cfg.robot_type, start_xy=start)
    fresh.update(start[0], start[1], 0.0, 0.0)
    assert fresh.index == 0 and fresh.state == "transit"
    a, b = route.waypoints[2], route.waypoints[3]
    restarted = RouteFollower(route, cfg.robot_type, start_xy=start)
    restarted.update((a.x + b.x) / 2, (a.y + b.y) / 2, 0.0, 0.0)
    assert restarted.index == 3 and restarted.state == "inspecting"


@pytest.fixture(scope="module")
def fleet16():
    """The shipped 16-robot fleet (generated routes) and its site."""
    import os

    from cps_fleet.fleet import default_fleet_path

    fleet = load_fleet(os.path.join(os.path.dirname(default_fleet_path()), "fleets", "fleet16.yaml"))
    return fleet, load_site(fleet.site_path)


@pytest.mark.parametrize("name", ["scout_1", "jackal_1", "champ_1", "iris_1", "scout_4"])
def test_the_follower_drives_a_generated_route_back_to_its_start_clear_of_the_site(fleet16, name):
    import numpy as np

    from cps_fleet.routes import Floor

    fleet, site = fleet16
    cfg, route = fleet.robot(name), fleet.route(name)
    validate_route(route, site, cfg.robot_type)
    robot = Robot(cfg.name, cfg.robot_type, cfg.initial_pose)
    follower, mux = (
        RouteFollower(route, cfg.robot_type, start_xy=(cfg.initial_pose.x, cfg.initial_pose.y)),
        VelocityMux(cfg.robot_type),
    )
    mux.set_estop(False)
    states, trace, t = [], [], 0.0
    while t < 300.0 and follower.state != "done":
        twist, flight = follower.update(robot.x, robot.y, robot.z, robot.yaw)
        if flight:
            robot.flight_command(flight)
        mux.on_auto(twist, t)
        robot.set_command(mux.update(t))
        robot.step(0.05)
        t += 0.05
        trace.append((robot.x, robot.y, robot.z))
        if not states or states[-1] != follower.state:
            states.append(follower.state)
    assert "inspecting" in states and states[-1] == "done", states
    assert math.hypot(robot.x - cfg.initial_pose.x, robot.y - cfg.initial_pose.y) < 0.5
    floor, trace = Floor(site), np.array(trace)
    if cfg.robot_type.is_aerial:
        assert robot.flight_state == "landed"
        assert set(floor.blocker_3d(trace, 0.3)) == {""}
    else:
        # The robot cuts corners a little: it stays 0.4 m clear where the route keeps 0.6 m.
        assert set(floor.blocker_2d(trace[:, :2], 0.4)) == {""}


def test_fleet_sim_names_the_generate_line_for_a_generated_start_a_site_change_blocks(fleet16):
    """fleet_sim re-checks the starts against the changed site; a generated robot has no line of its
    own, so the error points at the fleet file's generate: block."""
    from cps_sim.fleet_sim_node import initial_pose_error

    fleet, site = fleet16
    start = fleet.robot("champ_2").initial_pose
    crate = site.item("crate_2")
    blocked = site.moved("crate_2", start.x - crate.x, start.y - crate.y)
    error = initial_pose_error(fleet, blocked)
    assert error is not None and str(error).startswith(f"{fleet.path}:6: robots[") and "crate_2" in str(error)
    assert initial_pose_error(fleet, site) is None
