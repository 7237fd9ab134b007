"""The mission verdict from small synthetic mission folders: a clean mission passes, a map that
stops growing outside an outage fails, a missing or truncated CSV makes it INCOMPLETE (named, and
never a crash), and `make demo`'s exit code and console follow the verdict."""

import json
import os
import shutil

import pytest

from cps_experiments.demo import report_verdict
from cps_experiments.verdict import (
    DEMO_FILES,
    FAIL,
    INCOMPLETE,
    MAP_AGE_COLUMNS,
    PASS,
    judge,
    read_rows,
    read_verdict,
    write_verdict,
)

T0 = 1000.0  # wall time of the first map_age.csv row
ROBOTS = ("scout", "iris")


def _write_csv(path, columns, rows):
    path.write_text(",".join(columns) + "\n" + "".join(",".join(str(v) for v in row) + "\n" for row in rows))


def _map_ages(duration_s=60, age_of=lambda robot, t: 0.5):
    """One row per robot per second, the way MissionMonitor logs /twin/map_stats."""
    return [
        (f"{T0 + t:.3f}", robot, age_of(robot, t), "inspecting", 10 * t) for t in range(duration_s) for robot in ROBOTS
    ]


def _mission(folder, map_ages=None, f1_within_1_voxel=0.95, link_events=None):
    """A mission folder with every file the demo's verdict needs, each with a row."""
    folder.mkdir(exist_ok=True)
    for name in DEMO_FILES:
        if name.endswith(".csv") and name != "map_age.csv":
            _write_csv(folder / name, ("time_s", "robot", "value"), [(T0, "scout", 1.0)])
    _write_csv(folder / "map_age.csv", MAP_AGE_COLUMNS, _map_ages() if map_ages is None else map_ages)
    (folder / "map.bt").write_bytes(b"# Octomap OcTree binary file\n")
    (folder / "scores.json").write_text(json.dumps({"f1_exact": 0.7, "f1_within_1_voxel": f1_within_1_voxel}))
    if link_events:
        _write_csv(
            folder / "link_events.csv",
            ("mission_time_s", "wall_time_s", "event", "rate_mbps", "delay_ms", "jitter_ms", "loss_pct", "note"),
            link_events,
        )
    return folder


def test_a_clean_mission_passes(tmp_path):
    verdict = judge(_mission(tmp_path / "m"), ended_by="done")
    assert verdict.status == PASS, verdict
    assert verdict.failures == [] and verdict.exit_code == 0
    assert verdict.lines()[0].startswith("**PASS**")


def test_a_map_that_stops_growing_fails_as_stale(tmp_path):
    """The issue's case: the twin's map of every robot froze at 26 s and stayed so to the end."""
    frozen = _map_ages(75, lambda robot, t: 0.5 if t < 26 else t - 25.5)
    verdict = judge(_mission(tmp_path / "m", frozen), ended_by="done")
    assert verdict.status == FAIL and verdict.exit_code == 1
    stale = [f for f in verdict.failures if f.startswith("map stale")]
    assert len(stale) == 2 and any("iris" in f for f in stale) and any("scout" in f for f in stale)
    assert "29–74 s" in stale[0], stale
    assert verdict.lines()[0] == "**FAIL**" and any("map stale" in line for line in verdict.lines())


def test_a_stale_map_during_an_outage_and_3_s_after_it_is_not_a_failure(tmp_path):
    cut = [
        (0, T0, "start", 60, 0, 0, 0, ""),
        (20, T0 + 20, "cut", 60, 0, 0, 0, ""),
        (30, T0 + 30, "restore", 60, 0, 0, 0, ""),
    ]
    # Clouds stop at 20 s, the map catches up 2 s after the link is back.
    ages = _map_ages(60, lambda robot, t: t - 19.5 if 20 <= t < 32 else 0.5)
    assert judge(_mission(tmp_path / "ok", ages, link_events=cut), ended_by="done").status == PASS
    late = _map_ages(60, lambda robot, t: t - 19.5 if 20 <= t < 40 else 0.5)
    verdict = judge(_mission(tmp_path / "late", late, link_events=cut), ended_by="done")
    assert verdict.status == FAIL and "34–39 s" in verdict.failures[0], verdict.failures


def test_no_cloud_yet_is_judged_only_after_the_start_grace(tmp_path):
    starting = _map_ages(60, lambda robot, t: float("inf") if t < 5 else 0.5)
    assert judge(_mission(tmp_path / "ok", starting), ended_by="done").status == PASS
    never = _map_ages(60, lambda robot, t: float("inf") if robot == "iris" else 0.5)
    verdict = judge(_mission(tmp_path / "never", never), ended_by="done")
    assert verdict.status == FAIL and "iris" in verdict.failures[0] and "inf" in verdict.failures[0]


def test_a_map_server_restart_gets_the_start_grace_and_its_silence_is_noted(tmp_path):
    """Killed at 24 s, back at 26 s with fresh counters and no cloud for 5 s; then silent 40-45 s."""
    rows = [
        (f"{T0 + t:.3f}", robot, float("inf") if 26 <= t < 31 else 0.5, "inspecting", t if t < 24 else t - 26)
        for t in list(range(24)) + list(range(26, 40)) + list(range(45, 60))
        for robot in ROBOTS
    ]
    verdict = judge(_mission(tmp_path / "m", rows), ended_by="done")
    assert verdict.status == PASS, verdict
    assert verdict.notes == ["the map server published no statistics from record 39 s to 45 s (a restart; under 15 s)"]
    rows = [(t, robot, float("inf") if 26 <= float(t) - T0 < 50 else age, state, n) for t, robot, age, state, n in rows]
    assert judge(_mission(tmp_path / "m", rows), ended_by="done").status == FAIL


def test_a_map_server_that_publishes_nothing_for_long_fails(tmp_path):
    """The monitor's start mark at 0 s, the first statistics at 30 s (a map server busy starting up),
    its end mark at 80 s while the map server went silent at 60 s."""
    marks = [(f"{T0 + t:.3f}", robot, "nan", mark, "") for t, mark in ((0, "start"), (80, "end")) for robot in ROBOTS]
    rows = marks + [(f"{T0 + t:.3f}", robot, 0.5, "inspecting", t) for t in range(30, 60) for robot in ROBOTS]
    verdict = judge(_mission(tmp_path / "m", rows), ended_by="done")
    assert verdict.status == FAIL
    silent = "map stale: the map server published no statistics from record"
    assert verdict.failures == [f"{silent} 0 s to 30 s (over 15 s)", f"{silent} 59 s to 80 s (over 15 s)"]


def test_a_done_robot_is_not_judged(tmp_path):
    """A robot at the end of its route sends no new clouds: its map ages, and that is no failure."""
    rows = [
        (t, robot, 30.0 if float(t) - T0 > 40 else 0.5, "done" if float(t) - T0 > 40 else "inspecting", 0)
        for t, robot, _, _, _ in _map_ages()
    ]
    assert judge(_mission(tmp_path / "m", rows), ended_by="done").status == PASS


def test_map_f1_below_the_floor_fails_and_names_both_figures(tmp_path):
    verdict = judge(_mission(tmp_path / "m", f1_within_1_voxel=0.5), ended_by="done", f1_floor_within_1_voxel=0.9)
    assert verdict.status == FAIL
    assert verdict.failures == ["map F1 within ±1 voxel 0.500 below the floor 0.90 (voxel for voxel: 0.700)"]
    assert judge(tmp_path / "m", ended_by="done", f1_floor_within_1_voxel=0.4).status == PASS


def test_an_old_scores_json_is_judged_by_its_within_1_voxel_f1(tmp_path):
    folder = _mission(tmp_path / "m")
    (folder / "scores.json").write_text(json.dumps({"precision": 0.9, "recall": 0.5, "f1": 0.64}))
    verdict = judge(folder, ended_by="done", f1_floor_within_1_voxel=0.9)
    assert verdict.status == FAIL and "0.640" in verdict.failures[0]


def test_a_missing_csv_is_incomplete_and_named(tmp_path):
    folder = _mission(tmp_path / "m")
    (folder / "stats.csv").unlink()
    (folder / "map_age.csv").unlink()
    verdict = judge(folder, ended_by="done")
    assert verdict.status == INCOMPLETE and verdict.exit_code == 4
    assert "stats.csv is missing" in verdict.failures and "map_age.csv is missing" in verdict.failures


def test_a_truncated_csv_is_incomplete_and_its_rows_are_counted(tmp_path):
    folder = _mission(tmp_path / "m")
    text = (folder / "map_age.csv").read_text()
    (folder / "map_age.csv").write_text(text + f"{T0 + 61:.3f},scout,0.5\n{T0 + 62:.3f},iris,0.")
    rows, problems = read_rows(str(folder / "map_age.csv"))
    assert len(rows) == 120
    assert problems == ["map_age.csv: 2 truncated row(s) (line 122, 123), not counted in the figures"]
    verdict = judge(folder, ended_by="done")
    assert verdict.status == INCOMPLETE and verdict.failures == problems


def test_a_failure_found_wins_over_what_is_missing(tmp_path):
    """A map server silent all mission and no scores.json (no map): FAIL, both listed."""
    folder = _mission(
        tmp_path / "m",
        [(f"{T0 + t:.3f}", robot, "nan", mark, "") for t, mark in ((0, "start"), (60, "end")) for robot in ROBOTS],
    )
    (folder / "scores.json").unlink()
    verdict = judge(folder, ended_by="done")
    assert verdict.status == FAIL and verdict.exit_code == 1
    assert verdict.failures[0].startswith("map stale: the map server published no statistics from record 0 s")
    assert verdict.failures[1:] == ["scores.json is missing"]


def test_an_empty_folder_and_an_interrupted_mission_are_incomplete_not_a_crash(tmp_path):
    verdict = judge(tmp_path, ended_by="interrupted")
    assert verdict.status == INCOMPLETE
    assert len(verdict.failures) == len(DEMO_FILES) + 1
    assert verdict.failures[-1] == "the mission ended by interrupted before every route was done"


@pytest.mark.parametrize("status, code", [("pass", 0), ("stale", 1), ("missing", 4), ("none", 4)])
def test_demo_exit_code_and_console_follow_the_verdict(tmp_path, capsys, status, code):
    folder = tmp_path / "m"
    if status != "none":
        ages = _map_ages(60, lambda robot, t: t if status == "stale" and t > 30 else 0.5)
        _mission(folder, ages)
        if status == "missing":
            (folder / "allocation.csv").unlink()
        write_verdict(str(folder), judge(str(folder), ended_by="done"))
        assert read_verdict(str(folder)).status in (PASS, FAIL, INCOMPLETE)
    assert report_verdict("demo", str(folder)) == code
    out = capsys.readouterr()
    console = out.out + out.err
    assert {
        "pass": "verdict PASS",
        "stale": "map stale",
        "missing": "allocation.csv is missing",
        "none": "verdict INCOMPLETE",
    }[status] in console
    if code:
        assert "[demo] verdict" in out.err


@pytest.mark.slow
def test_the_report_of_a_folder_with_missing_and_truncated_csvs_says_incomplete(tmp_path):
    """The committed demo's CSVs, one cut off mid-row and one gone, no map: report.md is written,
    opens with INCOMPLETE and names both; nothing crashes."""
    from cps_bringup.cli import MissionResult, mission_args
    from cps_bringup.mission import MissionProgress
    from cps_experiments.report import write_mission_report

    demo = os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "docs", "results", "demo")
    out = tmp_path / "demo"
    out.mkdir()
    for name in (
        "stats.csv",
        "arrivals.csv",
        "physical_stats.csv",
        "physical_arrivals.csv",
        "link_events.csv",
        "link_state.csv",
    ):
        shutil.copy(os.path.join(demo, name), out / name)
    text = (out / "stats.csv").read_text()
    (out / "stats.csv").write_text(text[: len(text) // 2])
    robots = ["scout", "jackal"]
    progress = MissionProgress(
        robots,
        mission_state={r: "done" for r in robots},
        trajectories={"scout": ((-8.0, -6.0, 0.0),), "jackal": ((-8.0, 6.0, 0.0),)},
    )
    result = MissionResult(str(out), "done", 74.0, "loopback", None, progress, [], {})
    report = open(write_mission_report(result, mission_args("all", out=str(out), robots="scout,jackal"), 1.0)).read()
    head = report.split("## Robots")[0]
    assert head.startswith("# Mission report\n\n**INCOMPLETE**"), head
    assert "- allocation.csv is missing" in head and "- map_age.csv is missing" in head
    assert "- stats.csv: 1 truncated row(s)" in head and "- map.bt is missing" in head
    assert read_verdict(str(out)).status == INCOMPLETE


def test_map_stats_messages_logged_by_the_mission_monitor_are_what_the_verdict_reads(tmp_path):
    """MapStats as the map server publishes it (inf before a robot's first cloud) through the
    monitor's map_age.csv writer, then judged: iris's map froze at 10 s."""
    from cps_bringup.mission import map_age_rows
    from cps_fleet.csv_log import CsvLog
    from cps_msgs.msg import MapStats, RobotMapStats

    folder = _mission(tmp_path / "m")
    (folder / "map_age.csv").unlink()
    log = CsvLog(str(folder / "map_age.csv"), MAP_AGE_COLUMNS)
    for t in range(40):
        msg = MapStats(
            robots=[
                RobotMapStats(robot="scout", map_age_s=float("inf") if t < 2 else 0.4, clouds_inserted=max(t - 2, 0)),
                RobotMapStats(robot="iris", map_age_s=0.3 if t < 10 else t - 9.7, clouds_inserted=min(t, 10)),
            ]
        )
        for row in map_age_rows(msg, {"scout": "inspecting", "iris": "inspecting"}, T0 + t):
            log.write(row)
    log.close()
    rows, problems = read_rows(str(folder / "map_age.csv"))
    assert problems == [] and len(rows) == 80 and rows[0]["map_age_s"] == "inf"
    verdict = judge(folder, ended_by="done")
    assert verdict.status == FAIL and len(verdict.failures) == 1
    assert verdict.failures[0].startswith("map stale: iris's map") and "13–39 s" in verdict.failures[0]
