"""The report's link events from the CSVs the scenario runner and the manager write: outages with
their durations and the clouds the bridges counted lost or kept meanwhile, capacity steps with the
windows around them against the capacity in force and the manager's budget after them."""

import math

import numpy as np
import pytest

from cps_experiments.ledger import counter_series
from cps_experiments.link_report import NOT_COUNTED, bridge_outages, capacity_steps, scenario_outages, section
from cps_fleet import names

T0 = 1000.0  # wall time of mission second 0


def _event(mission_s, event, rate, note=""):
    return {
        "mission_time_s": str(mission_s),
        "wall_time_s": str(T0 + mission_s),
        "event": event,
        "rate_mbps": str(rate),
        "delay_ms": "0",
        "jitter_ms": "0",
        "loss_pct": "0",
        "note": note,
    }


EVENTS = [
    _event(0, "start", 60, "scenario demo (duplex)"),
    _event(25, "cut", 60),
    _event(35.2, "restore", 60),
    _event(60, "shape", 10),
    _event(80, "shape", 60),
]


def _windows():
    """1 s windows: 6 MB/s before 60 s, over the 1.1 MB/s budget for 2 s after the step, then 1 MB/s;
    nothing during the outage."""
    times = T0 + np.arange(0.5, 100.0, 1.0)
    totals = np.where(times - T0 < 60, 6.0, np.where(times - T0 < 62, 1.25, 1.0))
    totals[(times - T0 >= 25) & (times - T0 < 35)] = 0.0
    return times, totals


ALLOCATIONS = [
    {"stamp_s": str(T0), "budget_mbytes_per_s": "6.9"},
    {"stamp_s": str(T0 + 60.5), "budget_mbytes_per_s": "1.1"},
    {"stamp_s": str(T0 + 80.5), "budget_mbytes_per_s": "6.9"},
]


def test_outages_and_steps_from_the_runners_events():
    assert scenario_outages(EVENTS) == [(T0 + 25, 25.0, pytest.approx(10.2))]
    assert capacity_steps(EVENTS) == [(T0 + 60, 60.0, 60.0, 10.0), (T0 + 80, 80.0, 10.0, 60.0)]
    assert math.isnan(scenario_outages(EVENTS[:2])[0][2])  # still cut at the end


def test_bridge_transitions_make_outages_and_an_unended_one_says_so():
    rows = [
        {"up": "0", "since_s": "10.0", "peer": "robots"},
        {"up": "0", "since_s": "10.0", "peer": "robots"},
        {"up": "1", "since_s": "22.5", "peer": "robots"},
        {"up": "0", "since_s": "40.0", "peer": "robots"},
    ]
    outages = bridge_outages(rows)
    assert outages[0] == (10.0, 12.5, "robots") and outages[1][0] == 40.0 and outages[1][2] == "robots"
    lines = "\n".join(section([], rows, ALLOCATIONS, *_windows()))
    assert "still down at the end" in lines and "bridge saw robots down" in lines


def test_the_section_lists_the_outage_and_the_step_against_the_capacity_in_force():
    text = "\n".join(section(EVENTS, [], ALLOCATIONS, *_windows()))
    assert "| link cut (scenario) | 25.0 | 10.2 | 0.000 | " + NOT_COUNTED in text
    assert "the Zenoh bridge does not run yet" in text
    # 60 -> 10 (1.25 MB/s): no window over it before; after it the 1.25 MB/s windows are not over it.
    assert "| 60.0 | 60 → 10 | 0 of 10 | 0 of 10 | 1.250 | 1.10 |" in text
    # 10 -> 60: the 1 MB/s windows before are within 1.25 MB/s; the budget went back to 6.9 MB/s.
    assert "| 80.0 | 10 → 60 | 0 of 10 | 0 of 10 | 7.500 | 6.90 |" in text


def test_a_budget_left_above_the_new_capacity_is_said_in_the_step_row():
    stale = [dict(a, budget_mbytes_per_s="6.9") for a in ALLOCATIONS]
    text = "\n".join(section(EVENTS, [], stale, *_windows()))
    assert "| 60.0 | 60 → 10 | 0 of 10 | 0 of 10 | 1.250 | 6.90 (above the capacity) |" in text


def test_the_clouds_lost_in_an_outage_come_from_the_bridges_counters():
    """During the cut (25-35.2 s, counted to 3 s after) the robots' bridge held back 12 clouds and kept
    2 keyframes; the twin's bridge found 20 missing numbers: 14 withheld, 6 lost on the link."""

    def row(t, topic, key, value):
        return {"time_s": str(T0 + t), "node": "/b", "input_topic": topic, "key": key, "value": str(value)}

    sent, received = names.absolute(names.managed_cloud("scout")), names.absolute(names.managed_cloud_at_twin("scout"))
    rows = [
        row(10, sent, "ledger_bridge_out_dropped_outage", 0),
        row(30, sent, "ledger_bridge_out_dropped_outage", 12),
        row(31, sent, "ledger_bridge_out_backfill_kept", 2),
        row(10, received, "ledger_bridge_in_missed", 1),
        row(36, received, "ledger_bridge_in_missed", 21),
        row(90, received, "ledger_bridge_in_missed", 25),  # after the outage: not its
    ]
    text = "\n".join(section(EVENTS, [], ALLOCATIONS, *_windows(), counter_series(rows)))
    assert (
        "| link cut (scenario) | 25.0 | 10.2 | 0.000 | 18 (6 on the link, 12 held back without a keyframe) | 2 kept |"
        in text
    )


def test_no_scenario_and_no_link_state_adds_nothing():
    assert section([], [], ALLOCATIONS, *_windows()) == []
