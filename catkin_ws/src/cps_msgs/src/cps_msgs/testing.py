"""The ROS test harness: a private master on a free port and processes that never outlive a test.

The pytest fixtures in catkin_ws/src/conftest.py (`ros_master`, `ros`, `rospy_node`) use this.
"""
import time

from cps_msgs.processes import RosGraph, find_node, free_port, processes_named

__all__ = ["RosGraph", "find_node", "free_port", "processes_named", "wait_for"]


def wait_for(predicate, timeout_s=10.0, poll_s=0.05):
    """The first truthy value of `predicate()` within `timeout_s`, else None (assert on it)."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value or None
        time.sleep(poll_s)
