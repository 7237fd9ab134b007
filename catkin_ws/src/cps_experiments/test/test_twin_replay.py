"""The replay trials' ledger: every cloud the replay sent ends in one cause (inserted, superseded,
waiting, queue, decoder, tf, map server) or shows as unaccounted, never hidden."""

import math

import pytest

from cps_experiments.live_scaling import REPLAY_COLUMNS, _cell, replay_from_csv
from cps_experiments.markdown import write_csv
from cps_experiments.report import read_csv
from cps_experiments.twin_replay import CAUSES, CSV_COLUMNS, holds, judge_sweep, ledger, map_ages
from cps_msgs.msg import MapStats, RobotMapStats


def _row(**counts):
    return RobotMapStats(robot="a", **counts)


def test_the_causes_sum_to_what_was_sent_and_what_no_counter_saw_is_unaccounted():
    rows = [
        _row(
            clouds_received=10,
            clouds_inserted=4,
            clouds_superseded=3,
            clouds_dropped_tf=1,
            queue_length=1,
            clouds_dropped_decoder=1,
            clouds_missed_upstream=2,
        ),
        _row(clouds_received=5, clouds_inserted=2, clouds_superseded=2, clouds_dropped_invalid=1),
    ]
    counts = ledger(17, 0, rows)
    assert sum(counts[c] for c in CAUSES) == 17
    assert (counts["queue"], counts["unaccounted"], counts["received_not_ended"]) == (2, 0, 0)
    short = ledger(20, 1, rows)  # three sent clouds no counter saw
    assert short["unaccounted"] == 3 and short["replay_dropped"] == 1 and sum(short[c] for c in CAUSES) == 20


def test_a_robots_map_ages_count_while_its_replay_plays():
    """The replays' shards start and end apart: before a copy's replay (and its warm-up) and after
    it, nothing is there for the twin to insert, and its map age says nothing of the twin."""
    import genpy

    def stats(t, **ages):
        msg = MapStats(robots=[RobotMapStats(robot=r, map_age_s=a) for r, a in ages.items()])
        msg.header.stamp = genpy.Time.from_sec(t)
        return msg

    inf = float("inf")
    window = [stats(100.0, a=0.2, b=inf), stats(101.0, a=0.4, b=inf), stats(102.0, a=1.4, b=0.3), stats(103.0, b=0.2)]
    ages = map_ages(window, ["a", "b"], {"a": (99.0, 101.05), "b": (101.5, 103.5)}, warmup_s=0.5)
    assert ages == {"a": [0.2, 0.4], "b": [0.3, 0.2]}
    assert map_ages(window, ["a"], {})["a"] == [0.2, 0.4, 1.4]  # nothing known of its replay: every message


def test_a_trials_row_goes_through_fig13_lives_replay_csv_with_every_cause(tmp_path):
    row = {c: 1.5 for c in CSV_COLUMNS} | {f"clouds_{c}": 3 for c in CAUSES}
    row |= dict(label="fig13_live", robots=32, sent=9, inserted=3, received=9, superseded=3, dropped=0)
    row |= dict(age_p95_s=math.inf, oldest_over_median=math.nan, replay_limited=False, holds=False)
    row |= dict(ledger_balances=True, counted_by="the nodes' counters")
    path = tmp_path / "replay.csv"
    write_csv(path, REPLAY_COLUMNS, [[_cell({**row, "asked": 32}.get(c, "")) for c in REPLAY_COLUMNS]])
    (read,) = replay_from_csv(read_csv(path)).values()
    assert set(CSV_COLUMNS) <= set(read) and read["label"] == "fig13_live" and read["ledger_balances"] is True
    assert read["clouds_unaccounted"] == 3 and read["age_p95_s"] == math.inf and math.isnan(read["oldest_over_median"])


def test_a_trial_holds_on_every_robots_map_age_and_never_on_a_figure_not_measured():
    fine = dict(dropped_pct=0.5, superseded_pct=10.0, age_p95_s=0.6, oldest_robot_age_p95_s=0.9)
    assert holds(fine)
    assert not holds(fine | {"oldest_robot_age_p95_s": 1.2})  # the pooled p95 is fine, one robot is not
    assert not holds(fine | {"superseded_pct": 30.0}) and not holds(fine | {"dropped_pct": math.nan})


def _trial(robots, inserted_per_s, oldest_p95_s, age_p95_s=None, unaccounted=0):
    age_p95_s = oldest_p95_s if age_p95_s is None else age_p95_s
    return dict(
        robots=robots,
        dropped_pct=0.0,
        superseded_pct=10.0 if oldest_p95_s <= 1.0 else 60.0,
        age_p95_s=age_p95_s,
        oldest_robot_age_p95_s=oldest_p95_s,
        oldest_over_median=1.2,
        inserted_clouds_per_s=inserted_per_s,
        age_bar_s=1.5 * robots / inserted_per_s,
        clouds_unaccounted=unaccounted,
    )


def test_a_sweep_is_judged_from_its_measured_capacity_on():
    bends = [_trial(8, 70, 0.5), _trial(16, 140, 0.9), _trial(32, 150, 0.4, 0.3), _trial(64, 140, 1.3, 0.65)]
    bends[2]["superseded_pct"] = 40.0  # fresh, but a fraction of what was sent: not held
    verdict = judge_sweep(bends)
    assert (
        verdict["capacity"] == 16
        and verdict["fresh_capacity"] == 32
        and verdict["worst_fall"] == pytest.approx(1 - 140 / 150)
    )
    assert verdict["no_cliff"] and verdict["fresh_beyond"] and verdict["no_starving"] and verdict["ledger"]
    breaks = bends[:3] + [_trial(64, 20, 9.0, age_p95_s=6.0, unaccounted=3)]  # the cliff issue 37 found
    verdict = judge_sweep(breaks)
    assert not verdict["no_cliff"] and not verdict["fresh_beyond"] and not verdict["ledger"]


def test_the_replay_rows_run_again_leave_the_live_rows_as_they_are(tmp_path, monkeypatch):
    import json
    import os
    import shutil

    from cps_experiments import live_scaling

    results = os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "docs", "results")
    for name in ("fig13_live.csv", live_scaling.REPLAY_CSV, live_scaling.RUNS_JSON):
        shutil.copy(os.path.join(results, name), tmp_path / name)
    live_before = (tmp_path / "fig13_live.csv").read_text()
    row = {c: 0.5 for c in CSV_COLUMNS} | {f"clouds_{c}": 2 for c in CAUSES}
    row |= dict(label="fig13_live", robots=32, sent=14, inserted=2, received=14, superseded=2, dropped=0)
    row |= dict(replay_limited=False, holds=True, ledger_balances=True, counted_by="the nodes' counters")
    row |= dict(host_split="the new split")
    monkeypatch.setattr(live_scaling, "replay_rows", lambda sizes, *_a, **_k: {n: {**row, "robots": n} for n in sizes})
    live_scaling.rerun_replay(str(tmp_path), run_root=str(tmp_path / "runs"), sizes=(32, 64))
    assert (tmp_path / "fig13_live.csv").read_text() == live_before
    replayed = replay_from_csv(read_csv(tmp_path / live_scaling.REPLAY_CSV))
    assert sorted(replayed) == [32, 64] and replayed[64]["counted_by"] == "the nodes' counters"
    assert json.loads((tmp_path / live_scaling.RUNS_JSON).read_text())["replay_host_split"] == "the new split"
    assert "the new split" in (tmp_path / "fig13_live.md").read_text()


def test_a_replay_sends_tf_at_twice_its_fastest_clouds_within_the_simulators_rate():
    """The paper profile's 30 Hz camera clouds against the replay's 20 Hz tf waited in the map server
    for a transform after their stamp, and the next cloud superseded them (33 % at 8 robots, the twin
    half idle): its replay sends 2 x 30 Hz, capped at the simulator's 50 Hz odometry. Light stays at
    the floor (its 10 Hz camera)."""
    from cps_experiments.twin_replay import TF_RATE_HZ, replay_tf_rate_hz
    from cps_fleet.fleet import load_fleet
    from cps_sim.fleet_sim_node import FleetSimOptions

    fleet = load_fleet()
    assert fleet.with_profile("paper").profile.depth_camera.rate_hz * 2 > FleetSimOptions().odom_rate_hz
    assert replay_tf_rate_hz("paper") == FleetSimOptions().odom_rate_hz
    assert fleet.with_profile("light").profile.depth_camera.rate_hz * 2 <= TF_RATE_HZ
    assert replay_tf_rate_hz("light") == TF_RATE_HZ
