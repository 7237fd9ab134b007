"""make monitor-eval's headline is what ran: the live reports' recall and precision, and a first
view -> report time shorter than one detection cycle is impossible and set apart."""

import pytest

from cps_experiments.monitor_eval import DETECTION_CYCLE_S, live_totals, split_times

pytestmark = pytest.mark.unit


def test_times_shorter_than_a_detection_cycle_are_impossible_and_never_live_is_left_out():
    possible, impossible = split_times([12.0, None, -21.1, 3.6, 4.1, 69.5])
    assert possible == [12.0, 69.5] and impossible == [-21.1, 3.6, 4.1]
    assert DETECTION_CYCLE_S == 5.0


def test_the_live_reports_score_the_headline_and_without_them_recall_only():
    rows = [
        dict(made=3, time_to_report_s=[12.0, 8.4, None], live=None),
        dict(made=4, time_to_report_s=[7.0, 9.0, 10.0, 11.0], live=None),
    ]
    totals = live_totals(rows)
    assert (totals["matched"], totals["made"], totals["precision"]) == (6, 7, None)
    assert totals["recall"] == pytest.approx(6 / 7)
    rows = [dict(r, live=live) for r, live in zip(rows, ((2, 3, 3), (4, 5, 4)))]
    totals = live_totals(rows)
    assert (totals["matched"], totals["detected"]) == (6, 8) and totals["precision"] == pytest.approx(0.75)
