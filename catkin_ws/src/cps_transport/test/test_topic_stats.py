"""Topic statistics: the sliding window (unit) and the node against rostopic hz / bw (live)."""

import csv
import io
import math
import re
import threading
import time

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.testing import wait_for
from cps_transport.topic_stats import TopicWindow, has_header_first, stamp_ns_from_serialized

pytestmark = pytest.mark.waiting


def test_window_rate_bandwidth_latency():
    window = TopicWindow(2.0)
    for i in range(50):
        t = 10.0 + i * 0.1
        window.add(t, 1000 if i % 2 else 3000, stamp_s=t - (0.02 if i % 2 else 0.04))
    stats = window.snapshot(14.9)
    assert stats["messages"] == 21  # receive times within [12.9, 14.9]
    assert stats["rate_hz"] == pytest.approx(10.0)
    assert stats["mean_message_bytes"] == pytest.approx(2000, rel=0.05)
    assert stats["bandwidth_mbytes_per_s"] == pytest.approx(stats["rate_hz"] * stats["mean_message_bytes"] / 1e6)
    assert stats["latency_max_ms"] == pytest.approx(40.0)
    assert 20.0 < stats["latency_avg_ms"] < 40.0 and stats["latency_std_ms"] == pytest.approx(10.0, rel=0.1)
    assert stats["age_s"] == pytest.approx(0.0, abs=1e-9)
    quiet = window.snapshot(30.0)
    assert quiet["messages"] == 0 and quiet["rate_hz"] == 0.0 and math.isnan(quiet["latency_avg_ms"])
    assert TopicWindow(1.0).snapshot(0.0)["age_s"] == math.inf


def test_header_detection_and_stamp_peek():
    from nav_msgs.msg import Odometry
    from std_msgs.msg import String

    from cps_msgs.msg import CompressedPointCloud2

    assert has_header_first(Odometry._full_text)
    assert has_header_first(CompressedPointCloud2._full_text)
    assert not has_header_first(String._full_text)
    msg = Odometry()
    msg.header.stamp.secs, msg.header.stamp.nsecs = 1234, 500_000_000
    msg.header.frame_id = "odom"
    buffer = io.BytesIO()
    msg.serialize(buffer)
    assert stamp_ns_from_serialized(buffer.getvalue()) == 1234_500_000_000
    assert stamp_ns_from_serialized(b"\x00" * 5) is None


@pytest.mark.ros
def test_node_agrees_with_rostopic_hz_and_bw(ros, rospy_node, tmp_path):
    rospy = rospy_node
    from sensor_msgs.msg import PointCloud2

    from cps_msgs.msg import TopicStatsArray

    topic, csv_path = "/ts_test/cloud", tmp_path / "stats.csv"
    ros.start_node(
        "cps_transport",
        "topic_stats",
        name="topic_stats",
        namespace="/ts_test",
        params={
            "~topics": [topic, "/ts_test/silent"],
            "~window_s": 3.0,
            "~publish_rate_hz": 2.0,
            "~csv_path": str(csv_path),
        },
    )
    pub = rospy.Publisher(topic, PointCloud2, queue_size=10)
    stats = []
    sub = rospy.Subscriber(
        names.absolute(names.TISSUE_STATS, "/ts_test"), TopicStatsArray, stats.append
    )  # relative, in its namespace
    stop = threading.Event()

    def feed(rate_hz=20.0):
        msg = PointCloud2(height=1, width=2500, point_step=16, row_step=40000, data=bytes(40000))
        period, next_t = 1.0 / rate_hz, time.monotonic()
        while not stop.is_set():
            msg.header.stamp = rospy.Time.now()
            pub.publish(msg)
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))

    feeder = threading.Thread(target=feed, daemon=True)
    feeder.start()
    try:
        ros.wait_for_topic(topic)
        hz = ros.popen(["rostopic", "hz", topic, "-w", "60"], name="rostopic_hz")
        bw = ros.popen(["rostopic", "bw", topic, "-w", "60"], name="rostopic_bw")

        def full_window_reports():
            """Three reports of each over a full 60-message window (the last is dropped below)."""
            return (
                len(re.findall(r"window: 60", ros.output("rostopic_hz"))) >= 4
                and len(re.findall(r"window: 60", ros.output("rostopic_bw"))) >= 4
                and stats
            )

        assert wait_for(full_window_reports, 30.0), ros.output("rostopic_hz") + ros.output("rostopic_bw")
        ros.stop(hz)
        ros.stop(bw)
        # Reports with a full window; the last one is dropped (printed while rostopic shuts down).
        hz_values = [float(v) for v in re.findall(r"average rate: ([0-9.]+)\n.*window: 60", ros.output("rostopic_hz"))][
            :-1
        ]
        bw_values = re.findall(r"average: ([0-9.]+)(B|KB|MB)/s\n.*window: 60", ros.output("rostopic_bw"))[:-1]
        assert hz_values and bw_values, ros.output("rostopic_hz") + ros.output("rostopic_bw")
        rostopic_hz = float(np.median(hz_values))
        rostopic_mbytes = float(np.median([float(v) * {"B": 1e-6, "KB": 1e-3, "MB": 1.0}[u] for v, u in bw_values]))
        ours = [t for t in stats[-1].topics if t.topic == topic][0]
        silent = [t for t in stats[-1].topics if t.topic == "/ts_test/silent"][0]
        assert ours.rate_hz == pytest.approx(rostopic_hz, rel=0.05)
        assert ours.bandwidth_mbytes_per_s == pytest.approx(rostopic_mbytes, rel=0.1), (
            ros.output("rostopic_bw")[-600:] + ros.output("rostopic_hz")[-400:]
        )
        assert ours.mean_message_bytes == pytest.approx(40000 + 60, rel=0.01)
        assert 0.0 < ours.latency_avg_ms <= ours.latency_max_ms < 500.0 and ours.latency_std_ms >= 0.0
        assert ours.robot == "" and not ours.managed and ours.window_s == 3.0
        assert silent.messages == 0 and math.isinf(silent.age_s)
        with open(csv_path) as stream:
            rows = list(csv.DictReader(stream))
        cloud_rows = [row for row in rows if row["topic"] == topic]
        assert cloud_rows and float(cloud_rows[-1]["rate_hz"]) == pytest.approx(20.0, rel=0.1)
    finally:
        stop.set()
        feeder.join(2.0)
        sub.unregister()
        pub.unregister()


def test_default_topics_come_from_the_fleet():
    import importlib.machinery
    import importlib.util

    from cps_fleet.fleet import load_fleet
    from cps_harness.testing import find_node

    loader = importlib.machinery.SourceFileLoader("topic_stats_node", find_node("cps_transport", "topic_stats"))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name, loader))
    loader.exec_module(module)
    fleet = load_fleet()
    # Relative names, resolved in the node's namespace (the root namespace here).
    topics = [names.absolute(t) for t in module.fleet_topics(fleet)]
    for robot in fleet.robots:
        r = robot.name
        # The twin-side relay, never the physical side's topic: that would be a second copy on the link.
        assert names.absolute(names.managed_cloud_at_twin(r)) in topics
        assert names.absolute(names.managed_cloud(r)) not in topics
        assert names.absolute(names.robot_topic(r, names.ODOM)) in topics
        assert names.absolute(names.robot_topic(r, names.CAMERA_IMAGE)) not in topics
    assert names.TF in topics
