"""Fixtures of cps_link's tests (the workspace's ros_master/ros/rospy_node come from the top conftest)."""

import pytest

from cps_ros.processes import RosGraph


@pytest.fixture
def robots_graph():
    """A second, private master: the robots' side, while the session's master is the twin's."""
    graph = RosGraph()
    graph.start()
    try:
        yield graph
    finally:
        graph.close()
