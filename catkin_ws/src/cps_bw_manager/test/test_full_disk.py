"""A full disk (csv_path on /dev/full): topic_stats and the bandwidth manager report the lost CSV
once on /diagnostics and keep publishing /tissue/stats and /tissue/allocation."""

import time

import pytest

from cps_fleet import names
from cps_harness.testing import TopicRecorder

pytestmark = pytest.mark.ros


def _csv_report(msg):
    for status in msg.status:
        values = {kv.key: kv.value for kv in status.values}
        if status.name.endswith("/csv_log") and int(values.get("csv_rows_lost", 0)) >= 2:
            return status
    return None


def test_stats_and_allocation_keep_publishing_on_a_full_disk(ros, rospy_node):
    from diagnostic_msgs.msg import DiagnosticArray

    from cps_msgs.msg import BandwidthAllocationArray, TopicStatsArray

    diagnostics = TopicRecorder(names.DIAGNOSTICS, DiagnosticArray)
    stats = TopicRecorder(names.absolute(names.TISSUE_STATS), TopicStatsArray)
    allocation = TopicRecorder(names.absolute(names.ALLOCATION), BandwidthAllocationArray)
    try:
        stats_node = ros.start_node(
            "cps_transport",
            "topic_stats",
            name="topic_stats",
            params={"~topics": ["/full_disk/cloud"], "~publish_rate_hz": 4.0, "~csv_path": "/dev/full"},
        )
        manager = ros.start_node(
            "cps_bw_manager",
            "bandwidth_manager",
            name="bandwidth_manager",
            params={"~robots": ["scout"], "~update_rate_hz": 4.0, "~csv_path": "/dev/full"},
        )
        stats.wait_count(2, timeout_s=30)
        allocation.wait_count(2, timeout_s=30)
        seen = {}
        deadline = time.monotonic() + 15
        while len(seen) < 2 and time.monotonic() < deadline:
            for _, msg in diagnostics.take():
                status = _csv_report(msg)
                if status is not None:
                    seen[status.name] = status.message
            time.sleep(0.1)
        assert sorted(seen) == ["/bandwidth_manager/csv_log", "/topic_stats/csv_log"], seen
        assert all("No space left on device" in m for m in seen.values())
        counts = stats.count, allocation.count
        # Both publish at 4 Hz: 8 more each within 10 s, or they stopped.
        assert stats.wait_count(counts[0] + 8, timeout_s=10.0), (
            f"topic_stats stopped publishing {names.absolute(names.TISSUE_STATS)}"
        )
        assert allocation.wait_count(counts[1] + 8, timeout_s=10.0), (
            f"the bandwidth manager stopped publishing {names.absolute(names.ALLOCATION)}"
        )
        assert stats_node.poll() is None and manager.poll() is None
    finally:
        for recorder in (diagnostics, stats, allocation):
            recorder.close()
