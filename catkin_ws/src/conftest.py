"""Fixtures every package's tests share.

- `ros_master`: one private roscore for the whole test session (rospy can join one master per
  process); the environment points at it.
- `ros`: a RosGraph on that master that kills the processes a test started, even on failure.
- `rospy_node`: this test process as a rospy node on that master.
"""
import os

import pytest

from cps_harness.testing import RosGraph


@pytest.fixture(scope="session")
def ros_master():
    graph = RosGraph()
    graph.start()
    graph.point_this_process_here()
    os.environ["ROS_HOME"] = graph.home
    try:
        yield graph
    finally:
        graph.close()


@pytest.fixture
def ros(ros_master):
    graph = ros_master.attach()
    try:
        yield graph
    finally:
        graph.close()


@pytest.fixture(scope="session")
def rospy_node(ros_master):
    import rospy

    rospy.init_node("cps_pytest", anonymous=True, disable_signals=True)
    yield rospy
    rospy.signal_shutdown("tests done")
