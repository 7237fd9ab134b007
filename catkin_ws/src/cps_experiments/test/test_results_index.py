"""docs/results/README.md's headline rows come from the experiments' CSVs, not from hand edits."""

import pytest

from cps_experiments.run_all import MEASURED_HOW, fig13_live_rows, link_thesis_rows, write_index

pytestmark = pytest.mark.unit


def _link(arm, capacity, offered, received, over, phase="5 Mbit/s @ 40-60 s"):
    return dict(
        scenario="wifi_degraded", arm=arm, stream="link", capacity_mbps=str(capacity), capacity_mbytes_per_s="0.625",
        offered_mean_mbytes_per_s=str(offered), received_mean_mbytes_per_s=str(received),
        offered_over_capacity_windows=str(over), windows="20", phase=phase, robot="",
    )  # fmt: skip


def _stream(arm, received, phase="5 Mbit/s @ 40-60 s"):
    return dict(
        scenario="wifi_degraded", arm=arm, stream="video", capacity_mbps="5.0", robot="jackal", phase=phase,
        received_mean_mbytes_per_s=str(received),
    )  # fmt: skip


def test_link_thesis_row_gives_each_arm_in_the_5_mbit_phase_only_and_received_of_the_same_streams():
    rows = [
        _link("off", 5.0, 1.67, 0.16, 20),
        _stream("off", 0.155),
        _link("on_announced", 5.0, 0.52, 0.32, 2),
        _stream("on_announced", 0.215),
        _link("off", 60.0, 1.8, 1.8, 0, phase="60 Mbit/s @ 0-20 s"),
    ]
    (row,) = link_thesis_rows(rows)
    assert "manager off: offered 1.67, received 0.155 MB/s of managed streams (9%), 20 of 20" in row[2]
    assert (
        "on, capacity announced (oracle): offered 0.52, received 0.215 MB/s of managed streams (41%), 2 of 20" in row[2]
    )
    assert "1.80" not in row[2]
    assert link_thesis_rows([]) == []


def test_fig13_live_row_judges_both_arms_and_an_empty_cell_fails():
    base = dict(
        robots="16", link_mbps="60.0", dropped_fraction="0.0", teleop_p95_ms="52", f1_exact_fraction="0.926",
        min_hz="0.4", windows_over_budget="0",
    )  # fmt: skip
    rows = [
        {**base, "manager": "on", "min_window_hz": "0.2", "f1_fraction": "0.961"},
        {**base, "manager": "off", "min_window_hz": "", "f1_fraction": "0.99", "min_hz": "0.99"},
        {**base, "robots": "8", "manager": "on", "min_window_hz": "3", "f1_fraction": "1"},
    ]
    (row,) = fig13_live_rows(rows)
    assert "manager on: slowest robot 0.40 Hz mean, slowest 10 s window not recomputable" in row[2]
    assert "bar NOT met" in row[2] and "3.0 Hz" not in row[2]


def test_the_index_keeps_how_the_figures_are_measured(tmp_path):
    write_index(str(tmp_path))
    text = (tmp_path / "README.md").read_text()
    assert "\n".join(MEASURED_HOW) in text
    assert "| figure | window | tolerance / bar | where it is measured |" in text and "twin capacity" in text


def test_link_thesis_row_names_each_run_of_a_repeated_arm():
    """Three runs of the judged arm read as three unnamed "on, default" cells (2026-11-29): each says
    which run it is, in order."""
    rows = [_link("off", 5.0, 1.61, 0.47, 18)]
    for k, received in ((3, 0.12), (1, 0.19), (2, 0.14)):
        rows.append(dict(_link("on_default", 5.0, 0.2, received, 0), repeat=str(k)))
    (row,) = link_thesis_rows(rows)
    runs = [row[2].index(f"on, default (online estimate) run {k}: ") for k in (1, 2, 3)]
    assert runs == sorted(runs) and "manager off: offered 1.61" in row[2], row[2]
