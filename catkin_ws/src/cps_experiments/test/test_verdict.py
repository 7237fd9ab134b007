"""The mission verdict from synthetic mission folders (test/mission_files.py): a clean mission
passes; what a user would feel fails, naming the check, the robot and the time, with a non-zero
exit (a NaN F1, a budget left stale after a capacity step, a 5 s silence of the map server's
statistics, a map server that inserts but stops publishing, a robot whose clouds stop); a missing
or truncated file or a ledger that does not balance is INCOMPLETE, named, never a crash."""

import json
import math
import os
import shutil

import pytest
from mission_files import T0, event, mission

from cps_experiments.demo import report_verdict
from cps_experiments.run_files import read_rows
from cps_experiments.verdict import (
    DEMO_FILES,
    FAIL,
    INCOMPLETE,
    MAP_AGE_COLUMNS,
    PASS,
    judge,
    read_verdict,
    write_verdict,
)

pytestmark = pytest.mark.unit


def _judged(folder, **kwargs):
    verdict = judge(str(folder), ended_by="done", **kwargs)
    write_verdict(str(folder), verdict)
    return verdict


def _failed(verdict, name):
    return [c for c in verdict.checks if c["name"] == name and c["status"] == FAIL]


def test_a_clean_mission_passes_every_check(tmp_path):
    verdict = _judged(mission(tmp_path / "m"))
    assert verdict.status == PASS, verdict.failures
    assert verdict.failures == [] and verdict.exit_code == 0
    names = {c["name"] for c in verdict.checks}
    assert names >= {
        "map published and fresh",
        "map server heard",
        "clouds arriving",
        "operator video",
        "teleop",
        "map F1",
    }
    assert verdict.lines()[0] == "**PASS**: every check passed"
    assert report_verdict("demo", str(tmp_path / "m")) == 0


def test_a_nan_f1_fails_with_a_non_zero_exit(tmp_path, capsys):
    """NaN < 0.9 is False: the old verdict passed it."""
    folder = mission(tmp_path / "m", f1=(0.7, math.nan))
    verdict = _judged(folder)
    assert verdict.status == FAIL and verdict.exit_code == 1
    (failed,) = _failed(verdict, "map F1")
    assert "within ±1 voxel not measured" in failed["detail"]
    (folder / "scores.json").write_text(json.dumps({"f1_exact": None, "f1_within_1_voxel": 0.95}))
    assert _judged(folder).status == FAIL
    assert report_verdict("demo", str(folder)) == 1
    assert "map F1: FAIL, fleet, whole mission: voxel for voxel not measured" in capsys.readouterr().err


def test_a_budget_left_stale_after_a_capacity_step_fails_against_the_capacity_in_force(tmp_path):
    """The demo's 60 -> 10 Mbit/s step at 40 s: a manager that keeps its 6.93 MB/s budget plans on
    a link that now carries 1.25 MB/s. One that follows within the settling time passes."""
    steps = [event(0, "start", 60), event(40, "shape", 10)]
    stale = _judged(mission(tmp_path / "stale", events=steps, budget=lambda t: 6.93))
    assert stale.status == FAIL and stale.exit_code == 1
    (failed,) = _failed(stale, "budget within the capacity")
    assert failed["at_s"] == pytest.approx(45.5) and "6.93 MB/s above the 1.250 MB/s" in failed["detail"]
    followed = _judged(mission(tmp_path / "ok", events=steps, budget=lambda t: 6.9 if t < 42 else 1.2))
    assert followed.status == PASS, followed.failures


def test_the_robots_offering_more_than_the_capacity_in_force_fails(tmp_path):
    """Each robot offers 0.04 MB/s of clouds, jackal 0.05 MB/s of video: 0.13 MB/s, over 1 Mbit/s."""
    steps = [event(0, "start", 60), event(30, "shape", 1)]
    verdict = _judged(mission(tmp_path / "m", events=steps, budget=lambda t: 0.1))
    (failed,) = _failed(verdict, "offered load within the capacity")
    assert verdict.status == FAIL and "0.13 MB/s against 0.125 MB/s" in failed["detail"]


def test_a_5_s_silence_of_the_map_servers_statistics_fails(tmp_path):
    """A restart, a hang: the operator's map stood still. The old verdict only noted silences under 15 s."""
    times = [t for t in range(60) if not 30 < t < 35]  # nothing from 30 to 35 s
    verdict = _judged(mission(tmp_path / "m", stats_times=times))
    assert verdict.status == FAIL and verdict.exit_code == 1
    (failed,) = _failed(verdict, "map server heard")
    assert failed["at_s"] == pytest.approx(30.0) and "from 30.0 to 35.0 s (5.0 s, over 3 s)" in failed["detail"]
    assert "map server heard: FAIL, fleet, at 30.0 s" in verdict.failures[0]


def test_a_map_server_that_inserts_but_stops_publishing_fails(tmp_path):
    """Insertion stamps stay fresh (0.5 s) while the map as published ages from 25 s on."""
    verdict = _judged(mission(tmp_path / "m", published_age=lambda robot, t: 0.6 if t < 25 else t - 24.4))
    assert verdict.status == FAIL and verdict.exit_code == 1
    failed = _failed(verdict, "map published and fresh")
    assert {c["robot"] for c in failed} == {"scout", "jackal"}
    assert failed[0]["at_s"] == pytest.approx(28.0) and "from 28 to 59 s" in failed[0]["detail"]


def test_a_map_age_file_without_the_published_age_fails_the_check_it_cannot_make(tmp_path):
    """An older mission's map_age.csv: when the map was published is not known, so it is not passed."""
    folder = mission(tmp_path / "m")
    rows, _ = read_rows(str(folder / "map_age.csv"))
    old = ("time_s", "robot", "map_age_s", "mission_state", "clouds_inserted")
    (folder / "map_age.csv").write_text(
        ",".join(old) + "\n" + "".join(",".join(r[c] for c in old) + "\n" for r in rows)
    )
    verdict = _judged(folder)
    assert verdict.status == FAIL
    assert all("published_map_age_s" in c["detail"] for c in _failed(verdict, "map published and fresh"))


def test_a_stale_map_during_an_outage_and_3_s_after_it_is_not_a_failure(tmp_path):
    cut = [event(0, "start", 60), event(20, "cut", 60), event(30, "restore", 60)]

    def stale_until(name, until_s):
        """The link cut from 20 to 30 s; the published map catches up at `until_s`."""
        return _judged(
            mission(
                tmp_path / name,
                events=cut,
                published_age=lambda r, t: t - 19.5 if 20 <= t < until_s else 0.6,
                cloud_times=lambda robot: [k / 2 for k in range(120) if not 20 <= k / 2 < 30],
            )
        )

    ok = stale_until("ok", 32)
    assert ok.status == PASS, ok.failures
    late = stale_until("late", 40)
    assert late.status == FAIL
    assert _failed(late, "map published and fresh")[0]["at_s"] == pytest.approx(34.0)


def test_an_outage_the_scenario_did_not_cut_is_judged_and_one_without_a_scenario_is_excused(tmp_path):
    """demo_repeat run 4: the scenario restored the link at 30 s, the twin's bridge held it down
    from 31 s to the end and the map stood still: not excused. The same link state on a real link
    (no scenario) is all that is known of its outages: excused."""
    cut = [event(0, "start", 60), event(20, "cut", 60), event(30, "restore", 60)]
    frozen = {
        "published_age": lambda r, t: t - 19.5 if t >= 20 else 0.6,
        "cloud_times": lambda robot: [k / 2 for k in range(40)],
        "link_down": [(20.5, 30.2), (31.0, 99.0)],
    }
    verdict = _judged(mission(tmp_path / "frozen", events=cut, **frozen))
    assert verdict.status == FAIL
    assert _failed(verdict, "map published and fresh")[0]["at_s"] == pytest.approx(34.0)
    assert _failed(verdict, "clouds arriving")
    recovered = dict(frozen, published_age=lambda r, t: t - 19.5 if 20 <= t < 32 else 0.6, link_down=[(20.5, 30.2)])
    recovered["cloud_times"] = lambda robot: [k / 2 for k in range(120) if not 20 <= k / 2 < 30]
    assert _judged(mission(tmp_path / "recovered", events=cut, **recovered)).status == PASS
    real = dict(recovered, published_age=lambda r, t: t - 19.5 if 20 <= t < 32 else 0.6, link_down=[(20.0, 30.0)])
    assert _judged(mission(tmp_path / "real", events=[], **real)).status == PASS


def test_a_robot_whose_clouds_stop_fails_at_the_window_where_they_stopped(tmp_path):
    clouds = lambda robot: [k / 2 for k in range(120) if robot != "jackal" or k / 2 < 40]  # noqa: E731
    verdict = _judged(mission(tmp_path / "m", cloud_times=clouds))
    (failed,) = _failed(verdict, "clouds arriving")
    assert failed["robot"] == "jackal" and failed["at_s"] == pytest.approx(40.0)  # the first window without one
    assert "lowest 10 s window 40-50 s: 0 Hz < 1 Hz" in failed["detail"]


def test_a_done_robot_is_not_judged_on_its_map_age_nor_its_clouds(tmp_path):
    done = lambda robot, t: "done" if robot == "scout" and t > 30 else "inspecting"  # noqa: E731
    clouds = lambda robot: [k / 2 for k in range(120) if robot != "scout" or k / 2 < 31]  # noqa: E731
    verdict = _judged(
        mission(
            tmp_path / "m",
            state=done,
            published_age=lambda r, t: t - 30 if r == "scout" and t > 31 else 0.6,
            cloud_times=clouds,
        )
    )
    assert verdict.status == PASS, verdict.failures


def test_a_ledger_that_does_not_balance_is_incomplete_by_how_much(tmp_path):
    folder = mission(tmp_path / "m")
    counters = (folder / "counters.csv").read_text().replace(",ledger_bridge_in_out,120", ",ledger_bridge_in_out,110")
    (folder / "counters.csv").write_text(counters)
    verdict = _judged(folder)
    assert verdict.status == INCOMPLETE and verdict.exit_code == 4
    lines = [f for f in verdict.failures if f.startswith("ledger:")]
    assert len(lines) == 2 and all("10 unaccounted" in line or "20 unaccounted" in line for line in lines), lines
    (folder / "counters.csv").unlink()
    (folder / "physical_counters.csv").unlink()
    verdict = _judged(folder)
    assert verdict.status == INCOMPLETE
    assert any("counters not recorded: Draco encoder, rate limiter" in f for f in verdict.failures)


def test_a_missing_csv_is_incomplete_and_named(tmp_path):
    folder = mission(tmp_path / "m")
    (folder / "stats.csv").unlink()
    verdict = _judged(folder)
    assert verdict.status == INCOMPLETE and verdict.exit_code == 4
    assert "stats.csv is missing" in verdict.failures


def test_a_truncated_csv_is_incomplete_and_its_rows_are_counted(tmp_path):
    folder = mission(tmp_path / "m")
    text = (folder / "trajectories.csv").read_text()
    (folder / "trajectories.csv").write_text(text + "scout,1,0.5\niris,2,0.")
    rows, problems = read_rows(str(folder / "trajectories.csv"))
    assert len(rows) == 1
    assert problems == ["trajectories.csv: 2 truncated row(s) (line 3, 4), not counted in the figures"]
    verdict = _judged(folder)
    assert verdict.status == INCOMPLETE and verdict.failures == problems


def test_a_failure_found_wins_over_what_is_missing(tmp_path):
    folder = mission(tmp_path / "m", f1=(math.nan, math.nan))
    (folder / "stats.csv").unlink()
    verdict = _judged(folder)
    assert verdict.status == FAIL and verdict.exit_code == 1
    assert verdict.failures[-1] == "stats.csv is missing"


def test_an_empty_folder_and_an_interrupted_mission_are_a_failure_not_a_crash(tmp_path):
    verdict = judge(str(tmp_path), ended_by="interrupted")
    assert verdict.status == FAIL  # nothing measured: every check fails
    assert "the mission ended by interrupted before every route was done" in verdict.failures
    assert all(f"{name} is missing" in verdict.failures for name in DEMO_FILES)


@pytest.mark.parametrize("status, code", [("pass", 0), ("stale", 1), ("missing", 4), ("none", 4)])
def test_demo_exit_code_and_console_follow_the_verdict(tmp_path, capsys, status, code):
    folder = tmp_path / "m"
    if status != "none":
        mission(folder, published_age=lambda r, t: t if status == "stale" and t > 30 else 0.6)
        if status == "missing":
            (folder / "stats.csv").unlink()
        write_verdict(str(folder), judge(str(folder), ended_by="done"))
        assert read_verdict(str(folder)).status in (PASS, FAIL, INCOMPLETE)
    assert report_verdict("demo", str(folder)) == code
    out = capsys.readouterr()
    console = out.out + out.err
    assert {
        "pass": "verdict PASS",
        "stale": "map published and fresh: FAIL",
        "missing": "stats.csv is missing",
        "none": "verdict INCOMPLETE",
    }[status] in console
    if code:
        assert "[demo] verdict" in out.err


def test_map_stats_messages_logged_by_the_mission_monitor_are_what_the_verdict_reads(tmp_path):
    """MapStats as the map server publishes it through the monitor's map_age.csv writer, then
    judged: iris's published map froze at 10 s while its insertions stayed fresh."""
    from cps_bringup.mission import map_age_rows
    from cps_fleet.csv_log import CsvLog
    from cps_msgs.msg import MapStats, RobotMapStats

    folder = tmp_path / "m"
    folder.mkdir()
    log = CsvLog(str(folder / "map_age.csv"), MAP_AGE_COLUMNS)
    for t in range(40):
        msg = MapStats(
            robots=[
                RobotMapStats(
                    robot="scout", map_age_s=0.4, published_map_age_s=0.5, clouds_inserted=t, clouds_received=t
                ),
                RobotMapStats(
                    robot="iris",
                    map_age_s=0.3,
                    published_map_age_s=0.4 if t < 10 else t - 9.6,
                    clouds_inserted=t,
                    clouds_superseded=1,
                    clouds_missed_upstream=2,
                ),
            ]
        )
        for row in map_age_rows(msg, {"scout": "inspecting", "iris": "inspecting"}, T0 + t):
            log.write(row)
    log.close()
    rows, problems = read_rows(str(folder / "map_age.csv"))
    assert problems == [] and len(rows) == 80
    assert rows[-1]["clouds_superseded"] == "1" and rows[-1]["clouds_missed_upstream"] == "2"
    verdict = judge(str(folder), required_files=(), ended_by="done", f1_floor_within_1_voxel=None)
    (failed,) = _failed(verdict, "map published and fresh")
    assert failed["robot"] == "iris" and "from 16 to 39 s" in failed["detail"]


@pytest.mark.slow
def test_the_report_of_a_folder_with_missing_and_truncated_csvs_says_incomplete(tmp_path):
    """The committed demo's CSVs, one cut off mid-row and one gone, no map: report.md is written,
    opens with its verdict and names both; nothing crashes."""
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
    assert head.startswith("# Mission report\n\n**FAIL**"), head  # nothing to judge the map by
    assert "- allocation.csv is missing" in head and "- map_age.csv is missing" in head
    assert "- stats.csv: 1 truncated row(s)" in head and "- map.bt is missing" in head
    assert read_verdict(str(out)).status == FAIL
