"""The ROS test harness: a private master on a free port and processes that never outlive a test.

The pytest fixtures in catkin_ws/src/conftest.py (`ros_master`, `ros`, `rospy_node`) use this.
"""
from cps_msgs.processes import RosGraph, find_node, free_port, processes_named

__all__ = ["RosGraph", "find_node", "free_port", "processes_named"]
