"""fig13_live's sweep and its figures read back from a mission's files."""

import csv
import math

import pytest

from cps_experiments.live_scaling import (
    COMPARED,
    LiveRun,
    host_cpus_arg,
    measure_run,
    min_window_rate_hz,
    mission_argv,
    never_worse,
    setpoint_figures,
    spread,
    sweep,
    verdict,
)
from cps_fleet import names
from cps_fleet.config import ConfigError
from cps_fleet.fleet import default_fleet_path

pytestmark = pytest.mark.unit


def _write(path, columns, rows):
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(columns)
        writer.writerows(rows)


def _mission_files(folder, budget=7.0, windows=(1.0, 8.0, 2.0)):
    """Per window, the two robots share `windows` MB/s (as volume in topic_stats' 2 s window); the
    rostopic-style rate column says 40 MB/s, as a CPU-starved twin's burst would."""
    _write(
        folder / "stats.csv",
        ["time_s", "topic", "robot", "managed", "messages", "mean_message_bytes", "bandwidth_mbytes_per_s"],
        [
            [f"{t}.0", names.absolute(names.managed_cloud_at_twin(r)), r, "True", 10, mbps / 2 * 2.0 / 10 * 1e6, 40.0]
            for t, mbps in enumerate(windows)
            for r in ("a", "b")
        ],
    )
    _write(folder / "allocation.csv", ["time_s", "budget_mbytes_per_s"], [["0.0", budget]])
    # a: 10 clouds at 20 ms; b: 5 clouds at 40 ms (one at 400 ms); c: none reached the twin.
    arrivals = [(names.absolute(names.managed_cloud_at_twin("a")), "a", int(i * 1e9), i + 0.020) for i in range(10)]
    arrivals += [
        (names.absolute(names.managed_cloud_at_twin("b")), "b", int(i * 1e9), i + (0.4 if i == 4 else 0.040))
        for i in range(5)
    ]
    _write(folder / "arrivals.csv", ["topic", "robot", "stamp_ns", "receive_s"], arrivals)
    probes = [(names.absolute(names.COMMAND_PROBE), "", int(i * 1e8), i * 0.1 + 0.003) for i in range(20)]
    probes += [(names.absolute(names.robot_topic("a", names.POINTS_FILTERED)), "a", int(1e9), 1.05)]
    _write(folder / "physical_arrivals.csv", ["topic", "robot", "stamp_ns", "receive_s"], probes)


def test_the_figures_come_from_the_missions_files(tmp_path):
    _mission_files(tmp_path)
    summary = {"elapsed_s": 10.0, "clouds_inserted": {"a": 10, "b": 4}, "clouds_dropped": {"b": 1}}

    figures = measure_run(str(tmp_path), summary, ["a", "b", "c"], budget_mbytes_per_s=99.0)

    assert figures["budget_mbytes_per_s"] == 7.0  # the manager's own budget wins over the nominal one
    assert figures["windows"] == 3 and figures["windows_over_budget"] == 1
    assert figures["max_window_mbytes_per_s"] == pytest.approx(8.0)  # the volume, not the burst's rate
    assert figures["robots_reached"] == 2  # c is reported missing, not filled in
    assert figures["hz_per_robot"] == {"a": 1.0, "b": 0.5, "c": 0.0}
    assert figures["min_hz"] == 0.0
    assert figures["latency_p50_ms"] == pytest.approx(20.0, abs=0.5)
    assert 40.0 < figures["latency_p95_ms"] <= 400.0
    assert figures["teleop_probes"] == 20 and figures["teleop_p95_ms"] == pytest.approx(3.0, abs=0.1)
    assert figures["dropped_fraction"] == pytest.approx(1 / 15)
    assert figures["min_window_hz"] == 0.0  # c never reached the twin: 0 in its one (partial) window


def test_without_the_manager_the_nominal_budget_counts(tmp_path):
    _mission_files(tmp_path)
    (tmp_path / "allocation.csv").unlink()
    figures = measure_run(str(tmp_path), {"elapsed_s": 10.0}, ["a", "b"], budget_mbytes_per_s=1.5)
    assert figures["windows_over_budget"] == 2
    assert math.isnan(figures["dropped_fraction"])


def test_a_run_meets_the_bar_only_when_every_condition_holds():
    good = {
        "min_window_hz": 1.2,
        "windows_over_budget": 0,
        "f1_fraction": 0.97,
        "f1_exact_fraction": 0.96,
        "dropped_fraction": 0.0,
        "teleop_p95_ms": 12.0,
    }
    assert not any(c.failed for c in verdict(good).values())
    for key, bad in (
        ("min_window_hz", 0.9),
        ("min_window_hz", math.nan),
        ("windows_over_budget", 1),
        ("f1_fraction", 0.9),
        ("f1_exact_fraction", 0.9),
        ("dropped_fraction", 0.02),
        ("teleop_p95_ms", 51.0),
        ("f1_fraction", math.nan),
    ):
        assert any(c.failed for c in verdict({**good, key: bad}).values()), key
    old = {**good, "windows_cover_mission": False, "min_hz": 0.4}  # a row from before the judge
    assert verdict(old)["every robot ≥ 1 Hz in every 10 s window"].failed
    assert verdict({**old, "min_hz": 2.0})["every robot ≥ 1 Hz in every 10 s window"].failed  # not measured


def test_the_sweep_has_a_reference_and_both_links_each_way():
    runs = sweep((1, 16))
    assert LiveRun(16, None, False) in runs
    assert {(r.link_mbps, r.manager) for r in runs if r.robots == 16} == {
        (None, False),
        (60.0, True),
        (60.0, False),
        (10.0, True),
        (10.0, False),
    }
    assert sweep((4,), shaped=False) == [LiveRun(4, None, False)]


def test_a_fleet_too_small_for_the_sweep_is_refused(tmp_path):
    fleet = default_fleet_path()  # four robots
    argv = mission_argv(LiveRun(2, 10.0, False), fleet, str(tmp_path), 30)
    assert argv[argv.index("--link") + 1] == "10mbit" and argv[-2:] == ["--bandwidth-manager", "off"]
    with pytest.raises(ConfigError, match="asks for 16"):
        mission_argv(LiveRun(16, 60.0, True), fleet, str(tmp_path), 30)


def test_the_slowest_window_counts_not_the_mission_average():
    # a: 2 Hz for 30 s; b: 2 Hz but silent from 10 s to 20 s (mean 1.33 Hz, one window at 0 Hz).
    # Windows cover the whole span: a robot whose clouds stop 5 s before the end is seen.
    tail = [t for t in [i * 0.5 for i in range(61)] if t < 20.5]
    assert min_window_rate_hz({"a": [i * 0.5 for i in range(61)], "b": tail}, ["a", "b"], window_s=10.0) == 0.0
    a = [i * 0.5 for i in range(61)]
    b = [t for t in a if not 10.0 <= t < 20.0]
    assert min_window_rate_hz({"a": a, "b": b}, ["a", "b"], window_s=10.0) == 0.0
    assert min_window_rate_hz({"a": a, "b": a}, ["a", "b"], window_s=10.0) == 2.0
    assert min_window_rate_hz({"a": a}, ["a", "c"], window_s=10.0) == 0.0  # c never reached the twin
    assert min_window_rate_hz({}, ["a"], window_s=10.0) == 0.0


def test_the_windows_overlap_and_cover_the_tail():
    """Issue 36's plain judge: a 10 s silence straddling two back-to-back windows (5-15 s) is a
    window at 0 Hz, and so is one in the last 10 s of a 35 s run that whole windows left out."""
    a = [i * 0.5 for i in range(71)]  # 2 Hz for 35 s
    straddling = [t for t in a if not 5.0 <= t < 15.0]
    assert min_window_rate_hz({"a": straddling}, ["a"], window_s=10.0) == 0.0
    tail = [t for t in a if not 25.0 <= t < 35.0]
    assert min_window_rate_hz({"a": tail, "b": a}, ["a", "b"], window_s=10.0) == 0.0


def test_every_row_asks_for_the_same_host_split(tmp_path):
    fleet = default_fleet_path()
    split = host_cpus_arg({"physical": (0,), "digital": (1,)})
    assert split == "robots=0,twin=1"
    for run in (LiveRun(2, None, False), LiveRun(2, 60.0, True)):
        argv = mission_argv(run, fleet, str(tmp_path), 30, split)
        assert argv[argv.index("--host-cpus") + 1] == "robots=0,twin=1"
    assert host_cpus_arg({}) is None


def test_replay_rows_are_reported_apart_and_judged_on_the_twin_alone():
    from cps_experiments.live_scaling import _replay_section

    row = dict(
        robots=30, sent=100, inserted=90, superseded_pct=8.0, dropped_pct=2.0, age_p95_s=0.6,
        twin_cpu_s_per_s=0.9, replay_late_p95_s=0.02, replay_limited=False, holds=False, host_split="split",
    )  # fmt: skip
    text = "\n".join(_replay_section({32: row, 64: {**row, "robots": 64, "holds": True}}, "split"))
    assert "N = 32, 64 by replay" in text and "| 30 (asked 32) |" in text and "| 64 |" in text
    assert "no F1" in text and "split" in text


def test_every_row_plays_the_same_recorded_video_when_given(tmp_path):
    fleet = default_fleet_path()
    argv = mission_argv(LiveRun(2, 60.0, False), fleet, str(tmp_path), 30, None, "/x/video_trace.npz")
    assert argv[argv.index("--video-trace") + 1] == "/x/video_trace.npz"
    assert "--video-trace" not in mission_argv(LiveRun(2, 60.0, False), fleet, str(tmp_path), 30)


def test_setpoints_are_counted_per_stream_and_in_steady_state():
    rows = [{"stamp_s": "0.0", "robot": "a", "stream": "cloud", "level_sent": "1", "rate_sent": "1"}]
    rows += [
        {"stamp_s": f"{t}", "robot": "a", "stream": "video", "level_sent": "0", "rate_sent": "1"} for t in (20, 22)
    ]
    rows += [{"stamp_s": "40.0", "robot": "b", "stream": "cloud", "level_sent": "0", "rate_sent": "1"}]
    f = setpoint_figures(rows, elapsed_s=40.0, steady_from_s=15.0)
    assert f["setpoints_per_s"] == pytest.approx(4 / 40.0) and f["setpoint_messages_per_s"] == pytest.approx(5 / 40.0)
    assert f["steady_setpoints_max_per_stream_window"] == 2  # a's video twice within 5 s
    assert f["steady_setpoints_per_stream_window"] == pytest.approx(3 / 3 / (25.0 / 5.0))
    assert all(math.isnan(v) for v in setpoint_figures(None, 40.0, 15.0).values())


def test_the_watched_video_is_measured_at_the_twin(tmp_path):
    _mission_files(tmp_path)
    video = names.absolute(names.robot_topic("b", names.CAMERA_IMAGE_COMPRESSED))
    with open(tmp_path / "arrivals.csv", "a", newline="") as stream:
        csv.writer(stream).writerows([(video, "b", int(i * 0.5e9), i * 0.5 + 0.030) for i in range(18)])
    figures = measure_run(str(tmp_path), {"elapsed_s": 10.0}, ["a", "b"], 7.0, watched="b")
    assert figures["video_hz"] == pytest.approx(1.8) and figures["video_latency_p95_ms"] == pytest.approx(30.0, abs=1)
    # the clouds span 9 s: the judge's one partial window over that span, 18 frames in it
    assert figures["video_min_window_hz"] == pytest.approx(2.0, rel=1e-3)
    assert math.isnan(measure_run(str(tmp_path), {"elapsed_s": 10.0}, ["a", "b"], 7.0)["video_hz"])


def test_repeats_come_after_the_first_sweep_and_name_their_folder():
    runs = sweep((1, 16), repeats={16: 3})
    assert runs[:10] == sweep((1, 16))
    assert {r.name for r in runs[10:]} >= {"n16_60mbit_manager_on_r1", "n16_60mbit_manager_off_r2"}
    assert len(runs) == 10 + 2 * 5 and all(r.robots == 16 for r in runs[10:])


def _figures(**values):
    base = {key: 1.0 for key, _, _ in COMPARED}
    return {**base, **values}


def test_on_is_judged_against_off_beyond_the_measured_spread():
    measured = {
        LiveRun(16, 60.0, True): _figures(min_window_hz=1.0, teleop_p95_ms=20.0),
        LiveRun(16, 60.0, True, 1): _figures(min_window_hz=1.2, teleop_p95_ms=22.0),
        LiveRun(16, 60.0, False): _figures(min_window_hz=1.25, teleop_p95_ms=10.0),
        LiveRun(16, 60.0, False, 1): _figures(min_window_hz=1.25, teleop_p95_ms=12.0),
    }
    assert spread(measured)["min_window_hz"] == pytest.approx(0.2)
    row = never_worse(measured)[(16, 60.0)]
    assert row["min_window_hz"][2] == "same"  # 1.1 against 1.25: within the spread of 0.2
    assert row["teleop_p95_ms"][2] == "worse"  # 21 ms against 11 ms, spread 2 ms
    assert row["f1"][2] == "same"


def test_figures_printed_alike_are_never_called_different():
    """fig13_live called the manager worse on F1 within ±1 voxel at 0.982 against 0.983 (spread
    0.0005), and on 0.456 against 0.457 with no repeats: one unit of the printed digit is no difference."""
    measured = {
        LiveRun(16, 60.0, True): _figures(f1=0.9821, f1_exact=0.456, latency_p95_ms=115.4),
        LiveRun(16, 60.0, True, 1): _figures(f1=0.9826, f1_exact=0.456, latency_p95_ms=115.4),
        LiveRun(16, 60.0, False): _figures(f1=0.9830, f1_exact=0.457, latency_p95_ms=114.6),
        LiveRun(8, 60.0, True): _figures(f1=0.95),
        LiveRun(8, 60.0, False): _figures(f1=0.983),
    }
    row = never_worse(measured)[(16, 60.0)]
    assert [row[k][2] for k in ("f1", "f1_exact", "latency_p95_ms")] == ["same", "same", "same"]
    assert never_worse(measured)[(8, 60.0)]["f1"][2] == "worse"


def test_a_low_budget_is_explained_by_the_measured_estimate_and_unmanaged_traffic(tmp_path):
    """fig13_live (session 21, 16 robots on 10 Mbit/s): the report said the estimator "reads the
    latency that CPU queueing adds as congestion" whenever the budget was low, while that run's
    estimate was ~9.6 Mbit/s and 16 robots' odometry and tf took ~5.3 of it. The sentence now gives
    the two measured figures from link_estimate.csv, and says when they were not measured."""
    from cps_experiments.live_scaling import _differences

    _mission_files(tmp_path, budget=0.42)
    _write(tmp_path / "link_estimate.csv", ["stamp_s", "capacity_mbps", "unmanaged_mbps"],
           [[i, 9.5 + 0.1 * (i % 3), 5.3] for i in range(9)])  # fmt: skip
    figures = measure_run(str(tmp_path), {"elapsed_s": 10.0}, ["a", "b"], budget_mbytes_per_s=1.2)
    assert figures["capacity_estimate_mbps"] == pytest.approx(9.6) and figures["unmanaged_mbps"] == pytest.approx(5.3)
    figures.update(f1=0.98, f1_exact=0.7)
    lines = "\n".join(_differences({LiveRun(16, 10.0, True): figures}, 0.04))
    assert "the link's estimate was 9.6 Mbit/s" in lines and "5.3 Mbit/s" in lines
    assert "CPU queueing" not in lines
    figures.update(capacity_estimate_mbps=math.nan)
    assert "were not measured" in "\n".join(_differences({LiveRun(16, 10.0, True): figures}, 0.04))
