"""guarded_timer: a periodic callback that raises is logged, counted on /diagnostics and keeps running."""

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for

pytestmark = pytest.mark.ros


def test_a_failing_callback_keeps_its_timer_and_is_counted(rospy_node):
    from diagnostic_msgs.msg import DiagnosticArray

    from cps_ros.timers import FAILURE_KEY, guarded_timer

    calls = []

    def fail(_event):
        calls.append(1)
        raise OSError(28, "No space left on device")

    diagnostics = TopicRecorder(names.DIAGNOSTICS, DiagnosticArray)
    timer = guarded_timer(0.05, fail, "failing test timer")
    try:
        assert wait_for(lambda: len(calls) >= 10, timeout_s=10), f"the timer stopped after {len(calls)} calls"
        assert timer.failures >= 10 and "No space left" in timer.last_error

        def reported(msg):
            values = {kv.key: kv.value for status in msg.status for kv in status.values}
            return values.get("timer") == "failing test timer" and int(values.get(FAILURE_KEY, 0)) >= 2

        diagnostics.wait(reported, timeout_s=10, what=f"the failure count on {names.DIAGNOSTICS}")
    finally:
        timer.shutdown()
        diagnostics.close()
