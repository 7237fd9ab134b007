"""The one judge every report uses, on synthetic series: windows that cover the whole phase, rates
from a stream's own arrivals, phases matched by the scenario's own boundaries, and a NaN or a
missing value that fails its check."""

import math

import pytest

from cps_experiments import judge as J

pytestmark = pytest.mark.unit


def test_a_phase_6_ms_short_of_20_s_with_no_arrivals_in_its_second_half_has_a_lowest_window_of_0():
    """The issue's case: cut without overlap from the start, only full windows counted, this phase
    had one 10 s window and its last 9.994 s were never seen (a "lowest window" of twice the mean)."""
    arrivals = [0.25 * k for k in range(40)]  # 4 Hz for the first 10 s, then nothing
    low = J.lowest_window(arrivals, 0.0, 19.994, 10.0)
    assert low.count == 0 and low.rate_hz == 0.0
    assert low.end_s == pytest.approx(19.994) and not low.partial
    mean = J.mean_rate_hz(arrivals, 0.0, 19.994)
    assert mean == pytest.approx(40 / 19.994)
    assert not J.impossible_minimum(mean, low.rate_hz)
    assert J.impossible_minimum(mean, 4.0)  # the old table's figure: above the mean, impossible


def test_windows_overlap_cover_the_whole_span_and_a_short_span_is_one_partial_window():
    # Every 5 s while a window fits (the last of those ends at 25.0), and one more ending at 25.5.
    assert J.window_starts(0.0, 25.5, 10.0, step_s=5.0) == [0.0, 5.0, 10.0, 15.0, 15.5]
    found = J.windows([], 0.0, 25.5, 10.0, step_s=5.0)
    assert found[-1].end_s == 25.5 and found[-1].start_s == 15.5 and len(found) == 5
    assert all(not w.partial for w in found)
    short = J.windows([1.0, 2.0], 0.0, 4.0, 10.0)
    assert len(short) == 1 and short[0].partial and short[0].rate_hz == pytest.approx(0.5)
    assert J.windows([1.0], 5.0, 5.0, 10.0) == []


def test_windows_touching_an_outage_are_left_out_and_a_stream_that_stops_is_seen_at_its_end():
    arrivals = [0.5 * k for k in range(80)]  # 2 Hz, 0-39.5 s
    found = J.windows(arrivals, 0.0, 60.0, 10.0, exclude=[(20.0, 25.0)])
    assert not any(J.overlaps(w.start_s, w.end_s, [(20.0, 25.0)]) for w in found)
    low = J.lowest_window(arrivals, 0.0, 60.0, 10.0, exclude=[(20.0, 25.0)])
    assert low.rate_hz == 0.0 and low.start_s == 40.0


def test_means_and_windows_come_from_the_same_arrivals():
    arrivals = [0.1 * k for k in range(300)]  # 10 Hz for 30 s
    mean = J.mean_rate_hz(arrivals, 0.0, 30.0)
    windows = J.windows(arrivals, 0.0, 30.0, 10.0)
    assert mean == pytest.approx(10.0)
    assert min(w.rate_hz for w in windows) <= mean + 1e-9
    assert math.isnan(J.mean_rate_hz(arrivals, 5.0, 5.0))


def test_silences_are_the_gaps_longer_than_allowed_and_nothing_at_all_is_one_silence():
    times = [0, 1, 2, 3, 8, 9, 10]  # 5 s without a sample from 3 to 8
    assert J.silences(times, 0, 10, 3.0) == [(3, 8)]
    assert J.silences([], 0, 10, 3.0) == [(0, 10)]
    assert J.silences(times, 0, 10, 5.0) == []


EVENTS = [
    {"event": "start", "wall_time_s": "100", "rate_mbps": "60"},
    {"event": "shape", "wall_time_s": "120", "rate_mbps": "20"},
    {"event": "cut", "wall_time_s": "125", "rate_mbps": "20"},
    {"event": "shape", "wall_time_s": "140", "rate_mbps": "5"},
    {"event": "shape", "wall_time_s": "160", "rate_mbps": "60"},
]


def test_phases_are_the_scenarios_own_and_runs_are_matched_by_their_number_not_a_rounded_label():
    ours = J.phases(EVENTS, 181.2)  # this run ended at 81.2 s, the other at 80.4 s: "0-81 s" vs "0-80 s"
    theirs = J.phases(EVENTS, 180.4)
    assert [p.capacity_mbps for p in ours] == [60, 20, 5, 60] and ours[-1].end_s == 181.2
    assert [p.index for p in ours] == [0, 1, 2, 3]
    pairs, problems = J.match_phases(ours, theirs)
    assert len(pairs) == 4 and problems == []  # the recovery phase is compared, whatever its length
    assert J.capacity_in_force(ours)(150.0) == 5 and math.isnan(J.capacity_in_force(ours)(99.0))
    assert J.steps(ours) == [(120.0, 60, 20), (140.0, 20, 5), (160.0, 5, 60)]
    pairs, problems = J.match_phases(ours, ours[:3])
    assert len(pairs) == 3 and problems == ["phase 4 is in one run only"]
    other = [J.Phase(0, 0, 10, 60), J.Phase(1, 10, 20, 10)]
    assert J.match_phases(ours[:2], other)[1] == ["phase 2: 20 against 10 Mbit/s"]


def test_a_phase_starts_when_its_step_began_not_when_its_commands_had_run():
    # demo_repeat's runs 7 and 9: the 10 -> 60 Mbit/s step at 80 s was written at 80.9 s, and a
    # budget measured on the faster link at 80.8 s was judged against 10 Mbit/s
    events = [
        {"event": "start", "wall_time_s": "100", "began_wall_time_s": "100", "rate_mbps": "10"},
        {"event": "shape", "wall_time_s": "180.9", "began_wall_time_s": "180.0", "rate_mbps": "60"},
    ]
    phase_list = J.phases(events, 200.0)
    assert [(p.start_s, p.capacity_mbps) for p in phase_list] == [(100.0, 10), (180.0, 60)]
    assert J.capacity_in_force(phase_list)(180.8) == 60
    # files written before the column: when the commands had run
    old = [{k: v for k, v in e.items() if k != "began_wall_time_s"} for e in events]
    assert [p.start_s for p in J.phases(old, 200.0)] == [100.0, 180.9]


def test_nan_or_missing_fails_its_check_and_every_failure_names_the_check_the_robot_and_the_time():
    assert J.at_least("map F1", math.nan, 0.9).failed
    assert J.at_least("map F1", None, 0.9).failed
    assert "not measured" in J.at_least("map F1", float("nan"), 0.9).detail
    assert J.at_most("teleop", math.nan, 50.0).failed
    assert not J.at_least("map F1", 0.95, 0.9).failed
    failed = J.at_least("clouds arriving", 0.0, 1.0, robot="iris", at_s=42.0, unit=" Hz")
    line = failed.line()
    assert line.startswith("clouds arriving: FAIL, iris, at 42.0 s") and "0 Hz < 1 Hz" in line
    assert J.check("x", None).failed and not J.check("x", True).failed
    assert J.status_of([]) == J.FAIL and J.status_of([J.check("x", True)]) == J.PASS
    assert J.missing("") and J.missing(None) and J.missing("nan") and not J.missing(0.0)


def test_stats_windows_measure_any_topic_set_the_same_way_and_a_row_without_numbers_is_missing():
    rows = [
        {"time_s": "1", "topic": "/a/managed", "messages": "4", "mean_message_bytes": "500000"},
        {"time_s": "1", "topic": "/a/other", "messages": "100", "mean_message_bytes": "100"},
        {"time_s": "2", "topic": "/a/managed", "messages": "", "mean_message_bytes": ""},
    ]
    managed = J.stats_window_volumes(rows, lambda r: r["topic"].endswith("managed"), 2.0)
    assert managed[0] == (1.0, pytest.approx(1.0)) and math.isnan(managed[1][1])
    everything = J.stats_window_volumes(rows, lambda r: True, 2.0)
    assert everything[0][1] == pytest.approx(1.005)


def test_two_arms_differ_only_beyond_the_spread_and_the_printed_digit():
    assert J.printed_unit(0.982) == pytest.approx(0.001) and J.printed_unit(115.0) == pytest.approx(1.0)
    assert J.printed_unit(0.0) == 0.0 and J.printed_unit(math.nan) == 0.0
    assert J.compare(0.9822, 0.9830, True) == "same"  # prints 0.982 against 0.983
    assert J.compare(0.9700, 0.9830, True) == "worse"
    assert J.compare(0.9700, 0.9830, True, spread=0.02) == "same"
    assert J.compare(52.0, 11.0, False) == "worse" and J.compare(11.0, 52.0, False) == "better"
    assert J.compare(math.nan, 1.0, True) == "n/a"


def test_a_figure_that_misses_its_bar_never_prints_as_the_bar():
    assert J.printed_apart(35 / 37, 0.95) == "0.946"  # "0.95" against "≥ 0.95" read as met
    assert J.printed_apart(0.94999, 0.95) == "0.94999"
    assert J.printed_apart(0.95, 0.95) == "0.95" and J.printed_apart(35 / 36, 0.95) == "0.97"
    assert J.printed_apart(0.11, 0.2) == "0.11" and J.printed_apart(math.nan, 0.95) == "—"
