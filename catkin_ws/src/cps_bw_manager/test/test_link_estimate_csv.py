"""link_estimate.csv's rows, no ROS master: one value per column, and a report the estimator refused
says why (a live failure's CSV showed a link-limited interval that cut nothing, with no way to
tell a refused report from a taken one)."""

import math

from cps_bw_manager.manager_node import LINK_ESTIMATE_CSV_COLUMNS, link_estimate_csv_row
from cps_msgs.msg import LinkEstimate, LinkReport


def _row(**kw):
    estimate = LinkEstimate(capacity_mbps=19.1, estimate_mbps=19.1, mode="cruise", true_capacity_mbps=math.nan)
    report = LinkReport(interval_s=0.5, sender_interval_s=0.5, delivered_bytes=1_000_000, rtt_s=[0.002, 0.004])
    row = link_estimate_csv_row(12.5, estimate, report, **kw)
    assert len(row) == len(LINK_ESTIMATE_CSV_COLUMNS)
    return dict(zip(LINK_ESTIMATE_CSV_COLUMNS, row))


def test_a_row_has_one_value_per_column_and_says_why_a_report_was_refused():
    taken = _row(overuse="link_full")
    assert (taken["overuse"], taken["refused"], taken["delivered_mbps"]) == ("link_full", "", "16.0000")
    assert _row(refused="clock_step")["refused"] == "clock_step"
