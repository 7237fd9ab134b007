"""Dead-man, command timeout and e-stop on an injected clock: a step of the wall clock (NTP) must
neither keep a robot running nor be needed to stop it. Without ROS."""

import time

import pytest

from cps_fleet.fleet import load_fleet
from cps_sim.controllers import CommandGate, RouteFollower, VelocityMux
from cps_sim.robots import Twist

TYPES = load_fleet().robot_types

JUMPS_S = (-30.0, 30.0)


class SteppedClock:
    """A wall clock that steps by `jump_s` at `jump_at_s` (of true time `t`)."""

    def __init__(self, jump_s, jump_at_s):
        self.t, self.jump_s, self.jump_at_s = 0.0, jump_s, jump_at_s

    def __call__(self):
        return self.t + (self.jump_s if self.t >= self.jump_at_s else 0.0)


def _stop_time(make, feed, jump_s, last_command_at_s=1.0, dt_s=0.01):
    """True time at which the output is zero again after the last command, the clock stepping by
    `jump_s` just after it."""
    clock = SteppedClock(jump_s, jump_at_s=last_command_at_s + dt_s / 2)
    subject = make(clock)
    while clock.t <= 3.0:
        if clock.t <= last_command_at_s:
            feed(subject)
        moving = subject_output(subject).vx != 0.0
        if clock.t > last_command_at_s and not moving:
            return clock.t - last_command_at_s
        clock.t += dt_s
    return None


def subject_output(subject):
    return subject.update() if isinstance(subject, VelocityMux) else subject.command()


def _mux(mode):
    def make(clock):
        mux = VelocityMux(TYPES["wheeled_depth"], deadman_s=0.5, auto_timeout_s=0.5, clock=clock)
        mux.set_estop(False)
        mux.set_mode(mode)
        return mux

    return make


def _gate(clock):
    gate = CommandGate(timeout_s=0.5, clock=clock)
    gate.set_estop(False)
    return gate


FEEDERS = {
    "mux teleop": (_mux("teleop"), lambda mux: mux.on_teleop(Twist(vx=0.5))),
    "mux auto": (_mux("auto"), lambda mux: mux.on_auto(Twist(vx=0.5))),
    "fleet_sim gate": (_gate, lambda gate: gate.on_command(Twist(vx=0.5))),
}


@pytest.mark.parametrize("jump_s", JUMPS_S)
@pytest.mark.parametrize("which", sorted(FEEDERS))
def test_a_wall_clock_step_cannot_stretch_the_deadman(which, jump_s):
    """Even fed a clock that steps (what time.time() does under NTP), the output stops no later than
    the timeout; back steps stop it at once instead of ~30 s later."""
    make, feed = FEEDERS[which]
    stopped_after_s = _stop_time(make, feed, jump_s)
    assert stopped_after_s is not None and stopped_after_s <= 0.5 + 0.02, (which, jump_s, stopped_after_s)


@pytest.mark.parametrize("which", sorted(FEEDERS))
def test_on_a_steady_clock_the_deadman_stops_at_its_timeout(which):
    make, feed = FEEDERS[which]
    stopped_after_s = _stop_time(make, feed, 0.0)
    assert 0.5 - 0.02 <= stopped_after_s <= 0.5 + 0.02


def test_the_default_clock_is_monotonic():
    assert VelocityMux(TYPES["wheeled_depth"]).clock is time.monotonic
    assert CommandGate().clock is time.monotonic


def test_a_new_mux_or_gate_is_stopped_until_it_hears_the_estop_and_a_fresh_command():
    t = [0.0]
    mux = VelocityMux(TYPES["wheeled_depth"], clock=lambda: t[0])
    gate = CommandGate(clock=lambda: t[0])
    mux.on_auto(Twist(vx=0.5))
    gate.on_command(Twist(vx=0.5))
    assert mux.update().vx == 0.0 and gate.command().vx == 0.0  # e-stop state unknown
    mux.set_estop(False)
    gate.set_estop(False)
    t[0] = 0.1
    assert mux.update().vx > 0.0  # the auto command is still fresh
    assert gate.command().vx == 0.0  # sent before the state was known
    gate.on_command(Twist(vx=0.5))
    assert gate.command().vx == 0.5
    gate.set_estop(True)
    mux.set_estop(True)
    assert gate.command().vx == 0.0 and mux.update().vx == 0.0
    gate.on_command(Twist(vx=0.5))
    assert gate.command().vx == 0.0  # bypassing the mux does not help
    gate.set_estop(False)
    assert gate.command().vx == 0.0  # nor does a command sent while stopped


def test_a_restarted_route_controller_does_not_refly_a_landed_quadrotor():
    fleet = load_fleet()
    cfg = fleet.robot("iris")
    route = fleet.route("iris")
    start = (cfg.initial_pose.x, cfg.initial_pose.y)
    last = route.waypoints[-1]
    restarted = RouteFollower(route, cfg.robot_type, start_xy=start)
    twist, flight = restarted.update(last.x, last.y, 0.0, 0.0)
    assert flight is None and twist == Twist() and restarted.state == "done"
    fresh = RouteFollower(route, cfg.robot_type, start_xy=start)
    assert fresh.update(start[0], start[1], 0.0, 0.0)[1] == "takeoff"
    flying = RouteFollower(route, cfg.robot_type, start_xy=start)
    assert flying.update(last.x, last.y, 3.0, 0.0)[1] == "land"  # still airborne at the end: land it
