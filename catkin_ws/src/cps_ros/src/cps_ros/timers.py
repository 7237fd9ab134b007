"""Periodic callbacks that survive their own exceptions.

A rospy.Timer whose callback raises stops for good while the process stays alive (a full disk
once stopped /tissue/stats forever). `guarded_timer` runs the callback in a guard that catches
the exception, logs it (throttled), counts it and reports the count on /diagnostics, and keeps
the timer going."""

import time

import rospy

from cps_ros.fault_report import FaultReport

FAILURE_KEY = "timer_failures"
_LOG_EVERY_S = 5.0


class GuardedTimer:
    """A rospy.Timer calling `callback(event)` every `period_s`; an exception is logged at most
    every 5 s, counted in `failures` and reported on /diagnostics (`timer_failures`), and the
    timer goes on. One raised once the node is shutting down is not a failure."""

    def __init__(self, period_s, callback, name):
        self.name = name
        self.callback = callback
        self.failures = 0
        self.last_error = ""
        self._last_logged_s = -float("inf")
        self._report = FaultReport(f"timer {name}")
        self._timer = rospy.Timer(rospy.Duration(period_s), self._run)

    def _run(self, event):
        try:
            self.callback(event)
        except Exception as exc:  # any failure: count it, say it, and keep the timer alive
            if rospy.is_shutdown():
                # The node is ending: its topics and the processes it talks to are closing, and a
                # call that fails now is not a fault (every mission's end logged two or three).
                return
            self.failures += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            now = time.monotonic()
            if now - self._last_logged_s >= _LOG_EVERY_S:
                self._last_logged_s = now
                rospy.logerr(
                    f"{rospy.get_name()}: periodic '{self.name}' failed ({self.failures} so far), "
                    f"the timer goes on: {self.last_error}"
                )
        if self.failures:
            self._report.report(self.last_error, timer=self.name, **{FAILURE_KEY: self.failures})

    def shutdown(self):
        self._timer.shutdown()


def guarded_timer(period_s, callback, name):
    """A GuardedTimer (see there): every node's periodic callback goes through one."""
    return GuardedTimer(period_s, callback, name)
