"""A part of a node that failed (a periodic callback that raised, a CSV log turned off), reported
on /diagnostics; the guarded timers and the drop reports both report through it."""

import time

import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from cps_fleet import names
from cps_ros.publisher import Publisher


class FaultReport:
    """Reports the fault counters of one part of a node (a periodic callback that raised, a CSV log
    turned off) on /diagnostics as an ERROR status named `<node>/<part>`, at most once a second."""

    def __init__(self, part, period_s=1.0):
        self.part = part
        self.period_s = period_s
        self._last_s = -float("inf")
        self._pub = Publisher(names.DIAGNOSTICS, DiagnosticArray, queue_size=5)

    def report(self, message, **counts):
        now = time.monotonic()
        if now - self._last_s < self.period_s:
            return
        self._last_s = now
        status = DiagnosticStatus(
            level=DiagnosticStatus.ERROR,
            name=f"{rospy.get_name()}/{self.part}",
            hardware_id=self.part,
            message=message,
            values=[KeyValue(key=k, value=str(v)) for k, v in counts.items()],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = rospy.Time.now()
        try:
            self._pub.publish(array)
        except rospy.ROSException:  # shutting down
            pass
