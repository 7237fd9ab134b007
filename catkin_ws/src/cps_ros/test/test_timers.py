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


ENDING_NODE = """
import rospy
from cps_ros.timers import guarded_timer

rospy.init_node("guarded_timer_ending", anonymous=True, disable_signals=True)
calls = []

def fail_as_the_node_ends(_event):
    calls.append(1)
    while not rospy.is_shutdown():  # a call under way when the node ends finds its peer closed
        rospy.rostime.wallsleep(0.01)
    raise BrokenPipeError(32, "Broken pipe")

timer = guarded_timer(0.05, fail_as_the_node_ends, "ending test timer")
while not calls:
    rospy.rostime.wallsleep(0.01)
rospy.signal_shutdown("the node ends")
rospy.rostime.wallsleep(0.5)
print("calls", len(calls), "failures", timer.failures)
"""


def test_a_callback_failing_as_its_node_ends_is_not_a_failure(ros):
    """Every mission's end logged two or three failed timers: a periodic call that found its peer
    closed because the node was shutting down."""
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-c", ENDING_NODE], env=ros.env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "calls 1 failures 0" in result.stdout, result.stdout + result.stderr[-3000:]
    assert "periodic 'ending test timer' failed" not in result.stdout + result.stderr
