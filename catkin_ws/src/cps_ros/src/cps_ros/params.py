"""Private parameters read once, converted and range-checked, with errors that name them."""

import rospy

from cps_fleet.fleet import load_fleet


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
