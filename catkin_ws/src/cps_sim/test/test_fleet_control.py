"""The shared control library (cps_sim.fleet_control): every robot's mux and route tracker in one
process, each robot's state its own. Without ROS."""

import math
import os

import pytest
import yaml

from cps_fleet.config import ConfigError
from cps_fleet.fleet import default_fleet_path, load_fleet
from cps_fleet.site import load_site
from cps_sim.controllers import RouteTracker
from cps_sim.fleet_control import ControlLoop, FleetControl
from cps_sim.robots import Twist, spec_for

TYPES = load_fleet().robot_types


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


@pytest.fixture
def fleet():
    return load_fleet(profile="light")


@pytest.fixture
def control(fleet):
    clock = Clock()
    control = FleetControl(fleet, load_site(fleet.site_path), clock=clock)
    control.clock = clock
    control.set_estop(False)
    return control


def test_one_mux_and_route_tracker_per_robot_with_its_types_limits(fleet, control):
    assert control.robots == fleet.robot_names
    assert len({id(m) for m in control.muxes.values()}) == len(fleet.robots)
    # Each mux clamps to its robot type's limits: champ walks at 0.6 m/s at most, jackal 2.0.
    for name in ("champ", "jackal"):
        mux = control.mux(name)
        mux.set_mode("teleop")
        mux.on_teleop(Twist(vx=5.0))
        for _ in range(40):
            control.clock.now += 0.05
            mux.on_teleop(Twist(vx=5.0))
            out = mux.update()
        assert out.vx == pytest.approx(spec_for(fleet.robot(name).robot_type).limits.max_forward_mps)


def _drive(control, names, send):
    """Send a command to each robot twice, 50 ms apart (the acceleration limit ramps from zero)."""
    for _ in range(2):
        for name in names:
            assert send(control.mux(name), Twist(vx=0.3)) is None
            control.mux(name).update()
        control.clock.now += 0.05


def test_a_nan_command_for_one_robot_is_refused_and_the_others_drive_on(control):
    for name in ("scout", "jackal"):
        control.mux(name).set_mode("teleop")
    _drive(control, ("scout", "jackal"), lambda mux, twist: mux.on_teleop(twist))
    assert control.mux("scout").update().vx > 0 and control.mux("jackal").update().vx > 0
    reason = control.mux("scout").on_teleop(Twist(vx=float("nan")))
    assert reason and "nan" in reason.lower()
    control.clock.now += 0.05
    assert control.mux("scout").update() == Twist()  # holds
    assert control.mux("scout").dropped == 1
    assert control.mux("jackal").update().vx > 0  # untouched
    assert control.mux("jackal").dropped == 0
    assert control.mux("jackal").mode == "teleop" and control.mux("champ").mode == "auto"


def test_a_bad_mode_for_one_robot_leaves_every_mode_as_it_was(control):
    control.mux("iris").set_mode("teleop")
    with pytest.raises(ValueError, match="unknown control mode 'manual'"):
        control.mux("iris").set_mode("manual")
    assert {r: control.mux(r).mode for r in control.robots} == {
        "scout": "auto",
        "jackal": "auto",
        "champ": "auto",
        "iris": "teleop",
    }


def test_the_estop_stops_every_robot(control):
    _drive(control, control.robots, lambda mux, twist: mux.on_auto(twist))
    assert all(control.mux(r).update().vx > 0 for r in control.robots)
    control.set_estop(True)
    assert all(control.mux(r).update() == Twist() for r in control.robots)


def test_an_unknown_robot_is_named_with_the_known_ones(control):
    with pytest.raises(KeyError, match="no robot 'rover'.*scout, jackal, champ, iris"):
        control.mux("rover")


def test_a_bad_route_of_one_robot_is_refused_with_its_file_and_line(tmp_path):
    source = default_fleet_path()
    with open(source) as stream:
        doc = yaml.safe_load(stream)
    base = os.path.dirname(source)
    doc["site"] = os.path.join(base, doc["site"])
    for robot in doc["robots"]:
        robot["route"] = os.path.join(base, robot["route"])
    bad = tmp_path / "bad_route.yaml"
    bad.write_text("waypoints:\n  - {x: -8.5, y: -4.0}\n  - {x: 30.0, y: 0.0}\n")
    doc["robots"][2]["route"] = str(bad)
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    fleet = load_fleet(str(path))
    with pytest.raises(ConfigError) as err:
        FleetControl(fleet, load_site(fleet.site_path))
    assert f"{bad}:3:" in str(err.value) and "outside the hall" in str(err.value)


def test_route_trackers_follow_their_own_routes(fleet, control):
    scout, jackal = control.trackers["scout"], control.trackers["jackal"]
    assert scout.start() == "idle" and scout.update() == (None, None, None)  # nothing known yet
    for name, tracker in (("scout", scout), ("jackal", jackal)):
        pose = fleet.robot(name).initial_pose
        tracker.set_odom_in_map(pose.x, pose.y, 0.0, math.radians(pose.yaw_deg))
        tracker.set_odom(0.0, 0.0, 0.0, 0.0)
    command, flight, state = scout.update()
    assert state == "transit" and flight is None and command is not None
    first_scout = fleet.route("scout").waypoints[0]
    x, y, _, _ = scout.pose_in_map()
    assert (x, y) == pytest.approx((fleet.robot("scout").initial_pose.x, fleet.robot("scout").initial_pose.y))
    assert scout.follower.route.waypoints[0] == first_scout
    assert jackal.follower.route.path != scout.follower.route.path
    assert jackal.update()[2] == "transit" and scout.update()[2] is None  # a state is said once


def test_route_tracker_stops_sending_once_done():
    fleet = load_fleet(profile="light")
    tracker = RouteTracker(fleet.route("jackal"), TYPES["wheeled_depth"])
    last = fleet.route("jackal").waypoints[-1]
    tracker.set_odom_in_map(0.0, 0.0, 0.0, 0.0)
    tracker.follower.started, tracker.follower.index = True, len(fleet.route("jackal").waypoints)
    tracker.set_odom(last.x, last.y, 0.0, 0.0)
    command, _, state = tracker.update()
    assert state == "done" and command == Twist()  # the stop is sent once
    assert tracker.update() == (None, None, None)


def test_control_loop_runs_each_robots_ticks_at_its_rate_and_isolates_failures():
    calls, errors = {"a": 0, "b": 0}, []

    def tick(name):
        def run():
            calls[name] += 1
            if name == "a":
                raise RuntimeError("boom")

        return run

    loop = ControlLoop(lambda robot, task, exc: errors.append((robot, task, str(exc))))
    loop.add("a", "mux", 20.0, tick("a"), 0.0)
    loop.add("b", "mux", 10.0, tick("b"), 0.0)
    now = 0.0
    while now < 1.0 - 1e-9:
        wake = loop.step(now)
        now = max(wake, now)
    assert calls == {"a": 20, "b": 10}
    assert len(errors) == 20 and errors[0] == ("a", "mux", "boom") and loop.failures == {("a", "mux"): 20}


def test_control_loop_refuses_a_bad_rate():
    loop = ControlLoop(lambda *a: None)
    with pytest.raises(ValueError, match="b mux: rate must be a positive number"):
        loop.add("b", "mux", float("nan"), lambda: None, 0.0)
