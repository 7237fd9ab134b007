"""What the nodes share: validated private parameters, republishing rospy.AnyMsg without
deserializing it, and a small drop report on /diagnostics that the topic_stats node reads."""
import rospy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from cps_msgs.fleet import load_fleet

DROP_REPORT_TOPIC = "/diagnostics"
DROP_REPORT_KEY = "invalid_messages"


class ParameterError(ValueError):
    pass


def param(name, default, kind=float, low=None, high=None, low_open=False):
    """A private parameter read once, converted to `kind` and range-checked; the error names it."""
    value = rospy.get_param(name, default)
    if value is None:
        return None
    try:
        value = kind(value) if kind is not bool else _as_bool(value)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"parameter {rospy.resolve_name(name)}: {value!r} is not a {kind.__name__}") from exc
    if low is not None and (value < low or (low_open and value == low)):
        raise ParameterError(f"parameter {rospy.resolve_name(name)}: {value} must be {'>' if low_open else '>='} {low}")
    if high is not None and value > high:
        raise ParameterError(f"parameter {rospy.resolve_name(name)}: {value} must be <= {high}")
    return value


def _as_bool(value):
    if isinstance(value, bool):
        return value
    if str(value).lower() in ("true", "1", "yes"):
        return True
    if str(value).lower() in ("false", "0", "no"):
        return False
    raise ValueError(value)


def fleet_robot_of(topic_or_namespace, fleet=None):
    """The fleet robot a name belongs to (its first namespace segment), or ''."""
    segment = topic_or_namespace.strip("/").split("/", 1)[0]
    try:
        fleet = fleet or load_fleet(rospy.get_param("~fleet_file", None) or None)
    except Exception:  # no fleet file: nothing belongs to a robot
        return ""
    return segment if segment in fleet.robot_names else ""


def relay_class(connection_header):
    """A rospy.AnyMsg subclass that registers and serializes as the type in a connection header,
    so raw bytes go out on a publisher of the real type (rostopic, roscpp and typed subscribers work)."""
    return type("Relay_" + connection_header["type"].replace("/", "_"), (rospy.AnyMsg,), {
        "_type": connection_header["type"],
        "_md5sum": connection_header["md5sum"],
        "_full_text": connection_header.get("message_definition", ""),
        "__slots__": (),
    })


def relay_message(relay_cls, any_msg):
    out = relay_cls()
    out._buff = any_msg._buff
    return out


class DropReporter:
    """Counts malformed messages of one input topic; warns (throttled) and reports the count on
    /diagnostics once a second so the topic statistics can show it."""

    def __init__(self, input_topic, period_s=1.0):
        self.input_topic = input_topic
        self.invalid = 0
        self.processed = 0
        self.last_error = ""
        self._extra = {}
        self._pub = rospy.Publisher(DROP_REPORT_TOPIC, DiagnosticArray, queue_size=5)
        self._timer = rospy.Timer(rospy.Duration(period_s), self._report)

    def ok(self, **counters):
        self.processed += 1
        for key, value in counters.items():
            self._extra[key] = self._extra.get(key, 0) + value

    def count(self, **counters):
        """Adds to named counters without counting a processed message (e.g. frames skipped)."""
        for key, value in counters.items():
            self._extra[key] = self._extra.get(key, 0) + value

    def drop(self, reason):
        self.invalid += 1
        self.last_error = str(reason)
        rospy.logwarn_throttle(5.0, f"{rospy.get_name()}: dropped a message on {self.input_topic} "
                                    f"({self.invalid} so far): {reason}")

    def _report(self, _event=None):
        status = DiagnosticStatus(level=DiagnosticStatus.WARN if self.invalid else DiagnosticStatus.OK,
                                  name=rospy.get_name(), hardware_id=self.input_topic,
                                  message=self.last_error or "ok")
        values = {"input_topic": self.input_topic, DROP_REPORT_KEY: self.invalid, "processed": self.processed}
        values.update(self._extra)
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        array = DiagnosticArray(status=[status])
        array.header.stamp = rospy.Time.now()
        self._pub.publish(array)
