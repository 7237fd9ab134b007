"""The real-time loop and its clocks with a fake clock: no master, no sleeping."""

import pytest

from cps_sim.realtime import Periodic, PhysicsClock, run_realtime
from cps_sim.site_changes import SiteMove


class FakeClock:
    def __init__(self, now_s=100.0):
        self.now_s = now_s
        self.sleeps = []

    def __call__(self):
        return self.now_s

    def sleep(self, delay_s):
        self.sleeps.append(delay_s)
        self.now_s += delay_s


def test_loop_sleeps_until_the_steps_deadline_in_slices_of_at_most_the_period():
    clock = FakeClock()
    calls = []

    def step(now_s):
        calls.append(now_s)
        return now_s + 0.05

    run_realtime(step, period_s=0.02, clock=clock, sleep=clock.sleep, should_stop=lambda: len(calls) >= 3)
    assert clock.sleeps == pytest.approx([0.02, 0.02, 0.02])
    assert calls == pytest.approx([100.0, 100.02, 100.04])


def test_loop_calls_again_at_once_when_the_step_has_more_work_and_never_sleeps_for_a_past_deadline():
    clock = FakeClock()
    answers = iter([None, None, 99.0])
    calls = []

    def step(now_s):
        calls.append(now_s)
        return next(answers)

    run_realtime(step, period_s=0.02, clock=clock, sleep=clock.sleep, should_stop=lambda: len(calls) >= 3)
    assert len(calls) == 3 and clock.sleeps == []


def test_loop_does_not_step_when_stopped_before_it_starts():
    run_realtime(lambda now_s: pytest.fail("stepped"), 0.02, FakeClock(), FakeClock().sleep, lambda: True)


def test_periodic_runs_on_its_period_and_a_late_task_runs_once_not_in_a_burst():
    task = Periodic(0.1, first_s=10.0)
    assert not task.due(9.99) and task.due(10.0)
    task.done(10.0)
    assert task.next_s == pytest.approx(10.1)
    task.done(12.0)  # two seconds late
    assert task.next_s == pytest.approx(12.0)
    task.done(12.0)
    assert task.next_s == pytest.approx(12.1)


def test_physics_clock_integrates_the_lag_in_bounded_steps():
    physics = PhysicsClock(start_s=0.0, max_step_s=0.02, max_catch_up_s=1.0)
    steps = physics.steps(0.05)
    assert steps == pytest.approx([0.02, 0.02, 0.01])
    assert physics.sim_time_s == pytest.approx(0.05)
    assert physics.steps(0.05) == []


def test_physics_clock_waits_for_a_whole_step_unless_the_state_is_needed_now():
    physics = PhysicsClock(start_s=0.0, max_step_s=0.02, max_catch_up_s=1.0)
    assert physics.steps(0.005, min_lag_s=0.02) == [] and physics.sim_time_s == 0.0
    assert physics.steps(0.012, min_lag_s=0.02) == []
    assert physics.steps(0.012) == pytest.approx([0.012])  # exact: up to now
    assert physics.steps(0.035, min_lag_s=0.02) == pytest.approx([0.02, 0.003])
    assert physics.sim_time_s == pytest.approx(0.035)


def test_physics_clock_drops_a_stall_longer_than_the_catch_up_limit():
    physics = PhysicsClock(start_s=0.0, max_step_s=0.5, max_catch_up_s=1.0)
    assert sum(physics.steps(5.0)) == pytest.approx(1.0)
    assert physics.sim_time_s == pytest.approx(1.0)
    assert sum(physics.steps(5.1)) == pytest.approx(0.1)


def test_site_move_is_parsed_from_name_dx_dy():
    assert SiteMove.parse("crate_2:1.0:-0.5") == SiteMove("crate_2", 1.0, -0.5)
    with pytest.raises(ValueError, match="name:dx_m:dy_m"):
        SiteMove.parse("crate_2:1.0")


def test_step_timer_reports_mean_and_longest_pass_since_reset():
    from cps_sim.scheduling import StepTimer

    timer = StepTimer()
    assert timer.mean_ms == 0.0 and timer.max_ms == 0.0
    for seconds in (0.001, 0.003, 0.002):
        timer.add(seconds)
    assert timer.mean_ms == pytest.approx(2.0) and timer.max_ms == pytest.approx(3.0)
    timer.reset()
    timer.add(0.0005)
    assert timer.mean_ms == pytest.approx(0.5) and timer.max_ms == pytest.approx(0.5)
