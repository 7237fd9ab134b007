"""The test harness starts a private master and nodes, and leaves nothing behind."""

import os
import sys
import textwrap

import pytest

from cps_fleet import names
from cps_harness.testing import RosGraph, processes_named

TALKER = textwrap.dedent("""
    import rospy
    from std_msgs.msg import String
    rospy.init_node("talker")
    pub = rospy.Publisher("/chatter", String, queue_size=10)
    rate = rospy.Rate(20)
    i = 0
    while not rospy.is_shutdown():
        pub.publish(String(data=f"hello {i}"))
        i += 1
        rate.sleep()
""")

LISTENER = textwrap.dedent("""
    import sys, rospy
    from std_msgs.msg import String
    rospy.init_node("listener")
    msg = rospy.wait_for_message("/chatter", String, timeout=20)
    print("HEARD", msg.data, flush=True)
""")


@pytest.mark.ros
def test_talker_listener_and_no_process_left(tmp_path):
    graph = RosGraph()
    try:
        graph.start()
        port = graph.port
        graph.popen([sys.executable, "-c", TALKER], name="talker")
        graph.wait_for_topic("/chatter", timeout_s=20)
        listener = graph.popen([sys.executable, "-c", LISTENER], name="listener")
        assert listener.wait(30) == 0, graph.output("listener")
        assert "HEARD hello" in graph.output("listener")
        pids = [p.pid for p in graph.processes]
    finally:
        graph.close()
    leftover = processes_named(f"-p {port}", f"127.0.0.1:{port}")
    assert not leftover, leftover
    assert len(pids) == 3


@pytest.mark.ros
def test_cleanup_happens_when_the_test_body_fails():
    port = None
    with pytest.raises(AssertionError):
        with RosGraph() as graph:
            port = graph.port
            graph.popen([sys.executable, "-c", TALKER], name="talker")
            graph.wait_for_topic("/chatter", timeout_s=20)
            raise AssertionError("the test body fails")
    assert not processes_named(f"-p {port}", f"127.0.0.1:{port}")


@pytest.mark.ros
def test_a_node_that_dies_is_reported_while_waiting():
    with RosGraph() as graph:
        graph.popen([sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"], name="crasher")
        with pytest.raises(RuntimeError, match="crasher exited with 3"):
            graph.wait_for_topic("/never", timeout_s=10)


def test_messages_import_from_the_venv_python():
    assert sys.prefix.endswith(".venv"), f"tests must run in the project's venv, not {sys.prefix}"
    from cps_msgs.msg import BandwidthAllocationArray, CompressedPointCloud2, Octomap, TopicStatsArray  # noqa: F401
    from cps_msgs.srv import SetPriority, SetRate  # noqa: F401

    msg = CompressedPointCloud2(is_dense=True, compressed_data=b"\x01\x02")
    assert msg.is_dense and msg.compressed_data == b"\x01\x02"


@pytest.mark.ros
def test_a_private_master_leaves_this_process_pointed_where_it_was():
    before = {k: os.environ.get(k) for k in ("ROS_MASTER_URI", "ROS_IP")}
    with RosGraph() as graph:
        graph.wait_for_topic(names.ROSOUT_AGG, timeout_s=20)
        assert {k: os.environ.get(k) for k in before} == before
    assert {k: os.environ.get(k) for k in before} == before
