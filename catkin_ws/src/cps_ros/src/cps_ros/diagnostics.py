"""Counting malformed input and reporting the count on /diagnostics, where topic_stats reads it."""

import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from cps_fleet import names
from cps_ros.publisher import Publisher
from cps_ros.timers import guarded_timer

DROP_REPORT_TOPIC = names.DIAGNOSTICS
DROP_REPORT_KEY = "invalid_messages"


class DropReporter:
    """Counts malformed messages of one input topic; warns (throttled) and reports the count on
    /diagnostics once a second so the topic statistics can show it."""

    def __init__(self, input_topic, period_s=1.0, name=None):
        """`name`: the status's name (default the node's): a node's second reporter of one topic
        (the per-cloud ledger's) names itself apart, so readers of the node's own status find it."""
        self.input_topic = input_topic
        self.name = name
        self.invalid = 0
        self.processed = 0
        self.last_error = ""
        self._extra = {}
        self._pub = Publisher(DROP_REPORT_TOPIC, DiagnosticArray, queue_size=5)
        self._timer = guarded_timer(period_s, self._report, f"drop report {input_topic}")

    def ok(self, **counters):
        self.processed += 1
        for key, value in counters.items():
            self._extra[key] = self._extra.get(key, 0) + value

    def count(self, **counters):
        """Adds to named counters without counting a processed message (e.g. frames skipped)."""
        for key, value in counters.items():
            self._extra[key] = self._extra.get(key, 0) + value

    def gauge(self, **values):
        """Sets named values reported as they are (e.g. a store's fill), not added up."""
        self._extra.update(values)

    def drop(self, reason):
        self.invalid += 1
        self.last_error = str(reason)
        rospy.logwarn_throttle(
            5.0, f"{rospy.get_name()}: dropped a message on {self.input_topic} ({self.invalid} so far): {reason}"
        )

    def _report(self, _event=None):
        status = DiagnosticStatus(
            level=DiagnosticStatus.WARN if self.invalid else DiagnosticStatus.OK,
            name=self.name or rospy.get_name(),
            hardware_id=self.input_topic,
            message=self.last_error or "ok",
        )
        values = {"input_topic": self.input_topic, DROP_REPORT_KEY: self.invalid, "processed": self.processed}
        values.update(self._extra)
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = rospy.Time.now()
        self._pub.publish(array)
