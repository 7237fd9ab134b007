"""The command lane across two masters on loopback: each side runs its command-class bridge as a
process of its own (own Zenoh session and connection) beside the main bridge, so teleop never
waits behind clouds in a queue, a thread or an interpreter lock. Under 4 MB/s of clouds the
commands all arrive, with latency p95 printed and bounded; the command bridges carry no cloud, the
main bridges no command, and only the main bridge says whether the link is up."""

import os
import subprocess
import sys

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder, wait_for
from cps_link.zenoh_session import MAKE_CERTS, bridge_argv, bridge_node_name
from cps_ros.processes import find_node, free_port

pytestmark = [pytest.mark.ros, pytest.mark.slow]
HERE = os.path.dirname(os.path.abspath(__file__))
ROBOT = "scout"
TELEOP_HZ, MEASURE_S = 20.0, 10.0
# Loopback, no shaping: the bound is the lane's own cost plus scheduling on a shared 2-core machine.
TELEOP_P95_BOUND_MS = 100.0


def _teleop_rows(path):
    if not os.path.exists(path):
        return []
    with open(path) as stream:
        return [tuple(map(float, line.split())) for line in stream if len(line.split()) == 2]


def _subscriptions(master_uri, node):
    import rosgraph

    master = rosgraph.Master("/lane_probe", master_uri=master_uri)
    publishers, subscribers, _services = master.getSystemState()
    subs = {topic for topic, nodes in subscribers if "/" + node in nodes}
    pubs = {topic: nodes for topic, nodes in publishers}
    return subs, pubs


@pytest.mark.timeout(180)
def test_commands_cross_in_their_own_lane_while_clouds_load_the_main_one(
    rospy_node, ros, robots_graph, managed_cloud_load, tmp_path
):
    from cps_msgs.msg import CompressedPointCloud2, LinkState

    certs = str(tmp_path / "certs")
    subprocess.run([MAKE_CERTS, certs], check=True, capture_output=True)
    main_port, command_port = free_port(), free_port()
    for lane, port in (("main", main_port), ("command", command_port)):
        for graph, side, name in ((ros, "twin", f"bt_{lane}"), (robots_graph, "robots", f"br_{lane}")):
            argv = bridge_argv(
                sys.executable, side, "127.0.0.1", [ROBOT], certs, port, lane=lane, robots_address="127.0.0.1"
            )
            graph.popen(argv, name=name)
    managed_cloud_load(ROBOT)
    # 200 kB clouds at 20 Hz beside the fixture's: 4 MB/s through the main lane's bridges.
    robots_graph.popen(
        [
            sys.executable,
            find_node("cps_harness", "cloud_load"),
            f"{ROBOT}:200000:20",
            f"{names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(ROBOT))}",
            "__name:=heavy_load",
        ],
        name="heavy_load",
    )
    received = str(tmp_path / "teleop.txt")
    robots_graph.popen([sys.executable, find_node("cps_harness", "teleop_probe"), "recv", ROBOT, received], name="recv")
    link = TopicRecorder(names.absolute(names.LINK_STATE), LinkState)
    clouds = TopicRecorder(names.absolute(names.managed_cloud_at_twin(ROBOT)), CompressedPointCloud2)
    try:
        link.wait(lambda m: m.up, timeout_s=30, what="the link up")
        clouds.wait(lambda _m: clouds.count >= 20, timeout_s=30, what="clouds at the twin")
        ros.popen(
            [sys.executable, find_node("cps_harness", "teleop_probe"), "send", ROBOT, str(TELEOP_HZ)],
            name="send",
        )
        assert wait_for(lambda: len(_teleop_rows(received)) > 0, timeout_s=30), "no teleop at the robots"
        start = len(_teleop_rows(received))
        first_cloud_count = clouds.count
        assert wait_for(lambda: len(_teleop_rows(received)) >= start + TELEOP_HZ * MEASURE_S, timeout_s=MEASURE_S * 3)
        rows = _teleop_rows(received)[start:]
        latency_ms = np.array([(got - sent) * 1e3 for got, sent in rows])
        p50, p95 = np.percentile(latency_ms, 50), np.percentile(latency_ms, 95)
        print(
            f"\nteleop over the command lane, {len(rows)} commands while {clouds.count - first_cloud_count} clouds "
            f"crossed the main lane: p50 {p50:.1f} ms, p95 {p95:.1f} ms, max {latency_ms.max():.1f} ms"
        )
        assert clouds.count > first_cloud_count, "the main lane carried no cloud while commands crossed"
        assert p95 <= TELEOP_P95_BOUND_MS, f"teleop p95 {p95:.1f} ms"

        twin_subs, twin_pubs = _subscriptions(os.environ["ROS_MASTER_URI"], bridge_node_name("twin", "command"))
        main_subs, _ = _subscriptions(os.environ["ROS_MASTER_URI"], bridge_node_name("twin", "main"))
        assert bridge_node_name("twin", "main") != bridge_node_name("twin", "command")
        assert (
            names.absolute(names.robot_topic(ROBOT, names.CMD_VEL_TELEOP)) in twin_subs
            and names.absolute(names.robot_topic(ROBOT, names.CMD_VEL_TELEOP)) not in main_subs
        )
        assert not any("points" in t for t in twin_subs), twin_subs
        robot_subs, robot_pubs = _subscriptions(robots_graph.uri, bridge_node_name("robots", "command"))
        assert not any("points" in t for t in robot_subs), robot_subs
        for pubs, side in ((twin_pubs, "twin"), (robot_pubs, "robots")):
            assert pubs.get(names.absolute(names.LINK_STATE)) == ["/" + bridge_node_name(side, "main")], pubs.get(
                names.absolute(names.LINK_STATE)
            )
    finally:
        link.close()
        clouds.close()
