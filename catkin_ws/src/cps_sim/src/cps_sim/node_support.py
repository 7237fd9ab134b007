"""rospy glue the three cps_sim nodes share: start-up failures, parameters, the fleet, a fixed-rate
spin, Twist."""

import math
import sys
import time

import rospy
from geometry_msgs.msg import Twist as TwistMsg

from cps_fleet.config import ConfigError
from cps_fleet.fleet import load_fleet, robot_names_arg
from cps_fleet.site import load_site
from cps_sim.robots import Twist

# Repeated warnings (bad commands) are logged at most this often, per robot.
WARN_PERIOD_S = 2.0


class ThrottledLog:
    """`log(message)` at most once per `period_s` on the monotonic clock, for one robot's warnings."""

    def __init__(self, log, period_s, clock=time.monotonic):
        self.log, self.period_s, self.clock = log, period_s, clock
        self._last = -math.inf

    def __call__(self, message):
        now = self.clock()
        if now - self._last >= self.period_s:
            self._last = now
            self.log(message)


def fail(message):
    """Log a start-up error and exit non-zero (a clear message instead of a traceback)."""
    rospy.logfatal(message)
    sys.stderr.write(message + "\n")
    sys.stderr.flush()
    raise SystemExit(1)


def positive_param(name, default):
    value = rospy.get_param(name, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        fail(f"parameter {rospy.resolve_name(name)} must be a positive number, got {value!r}")
    return float(value)


def name_list(value):
    """A list parameter given as a YAML list or a comma-separated string."""
    items = value if isinstance(value, (list, tuple)) else str(value).split(",")
    return [str(item).strip() for item in items if str(item).strip()]


def load_fleet_param():
    """The fleet from ~fleet_file (and ~profile, ~robots), exiting with file:line on errors."""
    fleet_file = rospy.get_param("~fleet_file", "") or None
    profile = rospy.get_param("~profile", "") or None
    try:
        fleet = load_fleet(fleet_file, profile)
    except ConfigError as exc:
        fail(f"bad fleet file: {exc}")
    try:
        return robot_names_arg(fleet, name_list(rospy.get_param("~robots", "")))
    except ValueError as exc:
        fail(f"parameter ~robots: {exc}")


def load_site_for(fleet):
    try:
        return load_site(fleet.site_path)
    except ConfigError as exc:
        fail(f"bad site file: {exc}")


def spin_at(rate_hz, tick):
    """Call `tick()` at `rate_hz` until shutdown."""
    rate = rospy.Rate(rate_hz)
    while not rospy.is_shutdown():
        tick()
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break


def twist_from_msg(msg):
    return Twist(msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z)


def twist_to_msg(twist):
    msg = TwistMsg()
    msg.linear.x, msg.linear.y, msg.linear.z, msg.angular.z = twist.vx, twist.vy, twist.vz, twist.wz
    return msg
