"""docs/results/README.md's headline rows come from the experiments' CSVs, not from hand edits."""

import pytest

from cps_experiments.run_all import MEASURED_HOW, fig13_live_rows, link_thesis_rows, write_index

pytestmark = pytest.mark.unit


def _link(arm, capacity, offered, received, over):
    return dict(
        scenario="wifi_degraded", arm=arm, stream="link", capacity_mbps=str(capacity), capacity_mbytes_per_s="0.625",
        offered_mean_mbytes_per_s=str(offered), received_mean_mbytes_per_s=str(received),
        offered_over_capacity_windows=str(over), windows="20",
    )  # fmt: skip


def test_link_thesis_row_gives_each_arm_in_the_5_mbit_phase_only():
    rows = [
        _link("off", 5.0, 1.67, 0.16, 20),
        _link("on_announced", 5.0, 0.52, 0.32, 2),
        _link("off", 60.0, 1.8, 1.8, 0),
    ]
    (row,) = link_thesis_rows(rows)
    assert "manager off: offered 1.67, received 0.16 MB/s, 20 of 20" in row[2]
    assert "on, capacity announced: offered 0.52, received 0.32 MB/s, 2 of 20" in row[2]
    assert "1.80" not in row[2]
    assert link_thesis_rows([]) == []


def test_fig13_live_row_gives_both_arms_of_the_largest_fleet_and_an_empty_cell_is_nan():
    base = dict(robots="16", link_mbps="60.0", dropped_fraction="0.0", teleop_p95_ms="52", f1_exact_fraction="0.926")
    rows = [
        {**base, "manager": "on", "min_window_hz": "0.2", "f1_fraction": "0.961"},
        {**base, "manager": "off", "min_window_hz": "", "f1_fraction": "0.99"},
        {**base, "robots": "8", "manager": "on", "min_window_hz": "3", "f1_fraction": "1"},
    ]
    (row,) = fig13_live_rows(rows)
    assert "manager on: slowest 10 s window 0.2 Hz" in row[2] and "manager off: slowest 10 s window nan Hz" in row[2]
    assert "3.0 Hz" not in row[2]


def test_the_index_keeps_how_the_figures_are_measured(tmp_path):
    write_index(str(tmp_path))
    assert "\n".join(MEASURED_HOW) in (tmp_path / "README.md").read_text()
