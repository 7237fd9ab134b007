"""cps_ros.publisher.Publisher: a message that fails to serialize is lost, its topic is not."""

import pathlib
import re
import uuid

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for

WORKSPACE_SRC = pathlib.Path(__file__).resolve().parents[2]


def _stats(resolution_m, queue_length):
    from cps_msgs.msg import MapStats, RobotMapStats

    return MapStats(resolution=resolution_m, robots=[RobotMapStats(robot="scout", queue_length=queue_length)])


@pytest.mark.ros
@pytest.mark.parametrize("latch", [False, True])
def test_a_message_that_fails_to_serialize_leaves_the_topic_clean(rospy_node, latch):
    """A queue length of -1 in a uint32 field (the map server read it once between two counters):
    rospy raised, kept the message's first bytes in the topic's buffer and sent them ahead of every
    later message, so that the subscriber read nothing more. The next good message must arrive
    whole, and a subscriber that comes later gets the last good latched message."""
    import rospy

    from cps_msgs.msg import MapStats
    from cps_ros.publisher import Publisher

    topic = names.robot_topic(f"publisher_test_{uuid.uuid4().hex[:8]}", names.MAP_STATS)
    publisher = Publisher(topic, MapStats, queue_size=5, latch=latch)
    received = TopicRecorder(topic, MapStats)
    late = None
    try:
        assert wait_for(lambda: publisher.get_num_connections() >= 1, timeout_s=10), "no subscriber connected"
        publisher.publish(_stats(0.1, 1))
        received.wait(lambda m: m.resolution == pytest.approx(0.1), what="the first good message")
        with pytest.raises(rospy.ROSSerializationException):
            publisher.publish(_stats(0.2, -1))
        for resolution_m in (0.3, 0.4):
            publisher.publish(_stats(resolution_m, 3))
        last = received.wait(
            lambda m: m.resolution == pytest.approx(0.4), timeout_s=10, what="the good messages after the bad one"
        )
        got = [round(m.resolution, 3) for _, m in received.messages]
        assert got == [0.1, 0.3, 0.4], got
        assert last.robots[0].robot == "scout" and last.robots[0].queue_length == 3
        if latch:
            late = TopicRecorder(topic, MapStats)
            latched = late.wait(what="the latched message")
            assert latched.resolution == pytest.approx(0.4) and latched.robots[0].queue_length == 3
    finally:
        received.close()
        if late is not None:
            late.close()
        publisher.unregister()


def test_every_runtime_publisher_is_the_guarded_one():
    """A node that builds a message from live counters can hand rospy one bad field; each of its
    publishers must survive that, so none is a bare rospy.Publisher."""
    bare = []
    for package in sorted(WORKSPACE_SRC.glob("cps_*")):
        for path in [*package.glob("src/**/*.py"), *package.glob("nodes/*")]:
            if path.is_file() and re.search(r"\brospy\.Publisher\(", path.read_text(errors="replace")):
                bare.append(str(path.relative_to(WORKSPACE_SRC)))
    assert not bare, f"use cps_ros.publisher.Publisher in {bare}"
    assert (WORKSPACE_SRC / "cps_mapping" / "nodes" / "map_server").is_file()  # the scan saw the nodes


@pytest.mark.ros
def test_a_nodes_connected_subscribers_are_read_from_its_bus_info(rospy_node):
    """cps_ros.processes.subscribers_of: what the bringup waits on before it plays a recorded replay
    (the recorder connected to each topic the player publishes)."""
    from cps_msgs.msg import MapStats
    from cps_ros.processes import subscribers_of
    from cps_ros.publisher import Publisher

    topic = names.absolute(names.robot_topic(f"bus_info_test_{uuid.uuid4().hex[:8]}", names.MAP_STATS))
    me = rospy_node.get_name()
    assert topic not in subscribers_of(me, me)
    publisher = Publisher(topic, MapStats, queue_size=1)
    received = TopicRecorder(topic, MapStats)
    try:
        assert wait_for(lambda: me in subscribers_of(me, me).get(topic, ()), timeout_s=10), subscribers_of(me, me)
        assert subscribers_of("/no_such_node", me) == {}
    finally:
        received.close()
        publisher.unregister()
