"""The simulator's real-time loop, without ROS: testable with a fake clock and sleep.

`run_realtime` calls a step function until told to stop and sleeps until the step's next
deadline; `Periodic` is one fixed-rate task's deadline; `PhysicsClock` keeps simulated time
up with the wall clock in bounded steps and drops stalls it cannot catch up.
"""


def run_realtime(step, period_s, clock, sleep, should_stop):
    """Call `step(now_s)` until `should_stop()`.

    `step` returns the clock time it next has work (then the loop sleeps until then, at most
    `period_s` at a time, so new events are noticed) or None to be called again at once.
    `sleep(delay_s)` may return early (e.g. when a worker finishes).
    """
    while not should_stop():
        wake_s = step(clock())
        if wake_s is None:
            continue
        delay_s = wake_s - clock()
        if delay_s > 0:
            sleep(min(delay_s, period_s))


class Periodic:
    """A fixed-rate task's next deadline; a late task runs once, not in a burst."""

    def __init__(self, period_s, first_s):
        self.period_s = period_s
        self.next_s = first_s

    def due(self, now_s):
        return now_s >= self.next_s

    def done(self, now_s):
        self.next_s = max(self.next_s + self.period_s, now_s)


class PhysicsClock:
    """Simulated time that follows the wall clock in steps of at most `max_step_s`.

    A lag longer than `max_catch_up_s` (the loop stalled on a long render) is dropped rather
    than integrated, so robots do not jump; the real-time factor falls instead.
    """

    def __init__(self, start_s, max_step_s, max_catch_up_s):
        self.wall_start_s = start_s
        self.sim_time_s = 0.0
        self.max_step_s = max_step_s
        self.max_catch_up_s = max_catch_up_s

    def steps(self, now_s, min_lag_s=0.0):
        """The integration steps (s) that bring simulated time up to `now_s`; none while it lags by
        less than `min_lag_s` (a caller that needs the state at `now_s` passes 0)."""
        lag_s = now_s - (self.wall_start_s + self.sim_time_s)
        if lag_s < min_lag_s:
            return []
        if lag_s > self.max_catch_up_s:
            self.wall_start_s += lag_s - self.max_catch_up_s
            lag_s = self.max_catch_up_s
        out = []
        while lag_s > 1e-4:
            dt_s = min(lag_s, self.max_step_s)
            out.append(dt_s)
            self.sim_time_s += dt_s
            lag_s -= dt_s
        return out
