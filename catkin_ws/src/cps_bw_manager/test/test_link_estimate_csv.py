"""The manager node's handling of a link report, no ROS master: its time, and link_estimate.csv's rows: one value per column, and a report the estimator refused
says why (a live failure's CSV showed a link-limited interval that cut nothing, with no way to
tell a refused report from a taken one)."""

import math

from cps_bw_manager.manager_node import LINK_ESTIMATE_CSV_COLUMNS, link_estimate_csv_row, report_time_s
from cps_msgs.msg import LinkEstimate, LinkReport


def _row(**kw):
    estimate = LinkEstimate(capacity_mbps=19.1, estimate_mbps=19.1, mode="cruise", true_capacity_mbps=math.nan)
    report = LinkReport(
        interval_s=0.5,
        sender_interval_s=0.5,
        delivered_bytes=1_000_000,
        rtt_s=[0.002, 0.004],
        probe_refused="receiver_late:2",
    )
    row = link_estimate_csv_row(12.5, estimate, report, **kw)
    assert len(row) == len(LINK_ESTIMATE_CSV_COLUMNS)
    return dict(zip(LINK_ESTIMATE_CSV_COLUMNS, row))


def test_a_row_has_one_value_per_column_and_says_why_a_report_was_refused():
    taken = _row(overuse="link_full")
    assert (taken["overuse"], taken["refused"], taken["delivered_mbps"]) == ("link_full", "", "16.0000")
    assert _row(refused="clock_step")["refused"] == "clock_step"
    assert taken["probe_refused"] == "receiver_late:2"  # the trains the twin could not measure


def test_a_report_is_timed_by_its_stamp_not_by_when_the_manager_took_it():
    """Two reports 0.5 s apart taken back to back (as a callback that waited for the allocation's
    lock takes them) are two intervals, not a repeat (the estimator refuses a report less than a
    quarter interval after the last as a clock step)."""
    import rospy

    stamped = [LinkReport(interval_s=0.5, sender_interval_s=0.5) for _ in range(2)]
    stamped[0].header.stamp, stamped[1].header.stamp = rospy.Time(100.0), rospy.Time(100.5)
    taken_s = (100.9, 100.91)
    assert [report_time_s(m, t) for m, t in zip(stamped, taken_s)] == [100.0, 100.5]
    assert report_time_s(LinkReport(interval_s=0.5), 7.0) == 7.0  # unstamped: when it was taken
