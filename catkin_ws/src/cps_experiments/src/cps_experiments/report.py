"""The mission report: map quality against ground truth, link use and latency, plots, report.md.

Reads what the running system wrote (map.bt, stats.csv from cps_transport's topic_stats,
allocation.csv from cps_bw_manager) and the MissionResult of the supervisor.
"""

import csv
import json
import math
import os
from collections import defaultdict

import numpy as np

from cps_experiments.markdown import csv_float, markdown_table
from cps_fleet import names
from cps_transport.topic_stats import DEFAULT_WINDOW_S as STATS_WINDOW_S


def read_csv(path):
    if not os.path.exists(path):
        return []
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


def managed_link_windows(stats_rows, window_s=STATS_WINDOW_S):
    """(times, MB/s) per statistics publication (one a second): the managed topics' (clouds and, where
    measured, video) volume received in topic_stats' sliding window over its length (judge's
    stats_window_volumes: messages x mean size / window_s), not topic_stats' rostopic-style rate x
    size (a twin starved of CPU takes a backlog in one burst, and (n - 1) / span then reads many
    times what the link can carry). A publication without numbers is left out."""
    from cps_experiments.judge import stats_window_volumes

    pairs = [
        (t, v)
        for t, v in stats_window_volumes(stats_rows, lambda r: r.get("managed") == "True", window_s)
        if math.isfinite(v)
    ]
    return np.array([t for t, _ in pairs]), np.array([v for _, v in pairs])


def latency_summary(stats_rows, managed_only=True):
    """Per robot: avg, max and p95 of the windowed latency (ms) of its (managed) topic, over windows
    with data."""
    out = {}
    per_robot = defaultdict(lambda: defaultdict(list))
    for row in stats_rows:
        if (managed_only and row.get("managed") != "True") or not row.get("latency_avg_ms") or not row.get("robot"):
            continue
        for key in ("latency_avg_ms", "latency_max_ms", "latency_p95_ms"):
            value = csv_float(row[key])
            if math.isfinite(value):
                per_robot[row["robot"]][key].append(value)
    for robot, series in per_robot.items():
        out[robot] = {
            "avg_ms": float(np.mean(series["latency_avg_ms"])),
            "max_ms": float(np.max(series["latency_max_ms"])),
            "p95_ms": float(np.percentile(series["latency_p95_ms"], 95)),
        }
    return out


def first_arrivals(arrival_rows, topic_suffix=""):
    """{(robot, stamp_ns): first receive time s} of the arrival rows whose topic ends with topic_suffix."""
    out = {}
    for row in arrival_rows:
        if not row.get("robot") or not row.get("topic", "").endswith(topic_suffix):
            continue
        try:
            key, receive_s = (row["robot"], int(row["stamp_ns"])), float(row["receive_s"])
        except (KeyError, TypeError, ValueError):
            continue
        if key not in out or receive_s < out[key]:
            out[key] = receive_s
    return out


def latency_split(physical_arrival_rows, twin_arrival_rows, twin_topic_suffix="/" + names.POINTS_MANAGED):
    """Per robot, over the clouds that reached the twin and were seen on the robots' side (joined by
    capture stamp): clouds, capture -> twin avg/max ms, robot side avg ms, tissue + link avg ms.

    Per cloud, the robot side ends when the filtered cloud was received on the physical host, and
    no later than its arrival at the twin (a later receive is the statistics node's own queueing),
    so robot side + tissue + link = capture -> twin exactly and neither part is negative.
    """
    physical = first_arrivals(physical_arrival_rows)
    twin = first_arrivals(twin_arrival_rows, twin_topic_suffix)
    per_robot = defaultdict(list)
    for (robot, stamp_ns), twin_s in twin.items():
        if (robot, stamp_ns) not in physical:
            continue
        capture_s = stamp_ns * 1e-9
        filtered_s = min(physical[(robot, stamp_ns)], twin_s)
        per_robot[robot].append((twin_s - capture_s, filtered_s - capture_s, twin_s - filtered_s))
    out = {}
    for robot, rows in per_robot.items():
        ms = 1e3 * np.array(rows)
        out[robot] = {
            "clouds": len(rows),
            "total_avg_ms": float(ms[:, 0].mean()),
            "total_max_ms": float(ms[:, 0].max()),
            "robot_side_avg_ms": float(ms[:, 1].mean()),
            "tissue_link_avg_ms": float(ms[:, 2].mean()),
        }
    return out


TRAJECTORIES_CSV = "trajectories.csv"
TRAJECTORY_COLUMNS = ("robot", "sample", "x_m", "y_m", "z_m")
# Ray-cast the truth from one recorded position per this much travel (the samples are 0.5 s apart).
OBSERVABLE_POSITION_SPACING_M = 1.0


def write_trajectories(path, trajectories):
    """trajectories.csv: each robot's recorded base positions in `map` (the mission's poses, for the
    observable surface and for anyone re-scoring the map later)."""
    with open(path, "w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(TRAJECTORY_COLUMNS)
        for robot, points in sorted(trajectories.items()):
            for i, (x, y, z) in enumerate(points):
                writer.writerow((robot, i, f"{x:.3f}", f"{y:.3f}", f"{z:.3f}"))


def read_trajectories(path):
    """{robot: N x 3 positions} from trajectories.csv ({} if it is missing); unreadable rows are skipped."""
    out = defaultdict(list)
    for row in read_csv(path):
        point = (csv_float(row.get("x_m")), csv_float(row.get("y_m")), csv_float(row.get("z_m")))
        if row.get("robot") and all(math.isfinite(v) for v in point):
            out[row["robot"]].append(point)
    return {robot: np.array(points) for robot, points in out.items()}


def observable_surface_from_poses(fleet, ground_truth_path, trajectories):
    """The truth voxels in sight of where the robots' sensors were (cps_sim's ray-cast: base
    position + the sensor's mount height, within each robot type's max_range_m), or None without
    any position."""
    from cps_mapping.scoring import load_ground_truth
    from cps_sim.ground_truth import observable_from_positions, positions_every

    truth, resolution = load_ground_truth(ground_truth_path)
    seen = []
    for robot, points in sorted(trajectories.items()):
        if robot not in fleet.robot_names or not len(points):
            continue
        config = fleet.robot(robot)
        sensor_height_m = config.robot_type.sensor_mount.xyz_m[2]
        sensor = positions_every(points, OBSERVABLE_POSITION_SPACING_M) + [0.0, 0.0, sensor_height_m]
        seen.append(observable_from_positions(truth, resolution, sensor, config.robot_type.max_range_m))
    return np.unique(np.vstack(seen), axis=0) if seen else None


def score_saved_map(map_file, fleet, ground_truth_path, trajectories=None):
    """Load the saved map and score it against the simulator's ground truth at the map's resolution,
    exact and within ±1 voxel. With `trajectories` ({robot: positions in map}) the observable
    surface is ray-cast from them; without, it is the scored map's free space (and says so)."""
    from cps_fleet.site import load_site
    from cps_mapping.fused_map import FusedLogOddsMap
    from cps_mapping.scoring import score_fused_map
    from cps_sim.ground_truth import save_ground_truth

    resolution = fleet.mapping.resolution_m
    save_ground_truth(ground_truth_path, load_site(fleet.site_path), resolution)
    fused = FusedLogOddsMap.from_mapping_config(fleet.mapping)
    fused.load(map_file)
    observable = observable_surface_from_poses(fleet, ground_truth_path, trajectories) if trajectories else None
    return score_fused_map(fused, ground_truth_path, observable_centers_m=observable), fused


def observable_text(observable_from):
    """What the observable surface was computed from, for the report line."""
    from cps_mapping.scoring import OBSERVABLE_FROM_MAP, OBSERVABLE_FROM_POSES

    return {
        OBSERVABLE_FROM_POSES: "ray-cast in the ground truth from the robots' recorded positions at sensor "
        "height, any direction, within each robot type's max_range_m",
        OBSERVABLE_FROM_MAP: "relative to the scored map's own free space: a map that saw less is judged against less",
    }.get(observable_from, "every truth voxel with an empty face neighbour")


STREAMS = ("cloud", "video")


def allocated_streams(allocation_rows):
    """(times (N,), {(robot, stream): MB/s (N,)}) of allocation.csv: at each allocation instant, what
    the manager gave each robot's stream (a row without `stream`, from before the video was
    managed, is the cloud's); a stream absent at an instant had nothing. Keys robot by robot,
    cloud then video: the stacking order."""
    by_stamp = defaultdict(dict)
    for row in allocation_rows:
        stamp, value = csv_float(row["stamp_s"]), csv_float(row.get("bandwidth_mbytes_per_s"))
        key = (row["robot"], row.get("stream") or "cloud")
        by_stamp[stamp][key] = by_stamp[stamp].get(key, 0.0) + (value if math.isfinite(value) else 0.0)
    times = np.array(sorted(by_stamp))
    keys = sorted({k for values in by_stamp.values() for k in values}, key=lambda k: (k[0], STREAMS.index(k[1])))
    return times, {k: np.array([by_stamp[t].get(k, 0.0) for t in times]) for k in keys}


def plot_link(stats_rows, allocation_rows, budget_mbytes_per_s, png_path):
    """link.png: (1) every managed stream (each robot's cloud and video) stacked as the manager
    allocated it, against the budget, with the managed traffic received at the twin on top; (2)
    the allocated rates per stream; (3) the clouds' latency at the twin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
    t0 = min([csv_float(r["time_s"]) for r in stats_rows] + [csv_float(r["stamp_s"]) for r in allocation_rows] or [0.0])
    latencies = defaultdict(list)
    for row in stats_rows:
        if row.get("managed") == "True":
            latencies[row["robot"]].append(
                (
                    csv_float(row["time_s"]) - t0,
                    csv_float(row["latency_avg_ms"]) if row.get("latency_avg_ms") else math.nan,
                )
            )
    alloc_times, streams = allocated_streams(allocation_rows)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    robots = sorted({robot for robot, _ in streams})
    below = np.zeros(len(alloc_times))
    for (robot, stream), values in streams.items():
        colour = colours[robots.index(robot) % len(colours)]
        axes[0].fill_between(
            alloc_times - t0,
            below,
            below + values,
            step="post",
            color=colour,
            alpha=0.85 if stream == "cloud" else 0.4,
            hatch=None if stream == "cloud" else "//",
            lw=0,
            label=f"{robot} {stream}",
        )
        below = below + values
    times, totals = managed_link_windows(stats_rows)
    axes[0].plot(times - t0, totals, "k-", lw=1.5, label="received at the twin (managed)")
    axes[0].axhline(budget_mbytes_per_s, color="r", ls="--", label=f"budget {budget_mbytes_per_s:.2f} MB/s")
    axes[0].set_ylabel("allocated MB/s (stacked)")
    rates = defaultdict(list)
    for row in allocation_rows:
        key = f"{row['robot']} {row.get('stream') or 'cloud'}"
        rates[key].append((csv_float(row["stamp_s"]) - t0, csv_float(row["rate_hz"])))
    for key, series in sorted(rates.items()):
        series = np.array(series)
        axes[1].step(series[:, 0], series[:, 1], where="post", label=key, ls="-" if key.endswith("cloud") else ":")
    for robot, series in sorted(latencies.items()):
        series = np.array(series)
        axes[2].plot(series[:, 0], series[:, 1], label=robot)
    axes[1].set_ylabel("allocated Hz")
    axes[2].set_ylabel("cloud latency avg ms")
    axes[2].axhline(100, color="r", ls="--", label="paper's bound 100 ms")
    axes[2].set_xlabel("mission time, s")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right", ncol=2)
    fig.suptitle("Digital tissue during the mission (managed streams: clouds and video)")
    fig.tight_layout()
    fig.savefig(png_path, dpi=110)
    plt.close(fig)


MISSION_JSON = "mission.json"


def mission_summary(result, fleet, wall_time_s):
    """What only the supervisor knows of the mission, for mission.json: the report is then a function
    of the mission folder alone (and can be written again, by a newer judge, from it)."""
    progress = result.progress
    robots = {}
    for robot in fleet.robot_names:
        path = np.array(progress.trajectories.get(robot) or [(math.nan,) * 3])
        length = float(np.nansum(np.linalg.norm(np.diff(path, axis=0), axis=1))) if len(path) > 1 else 0.0
        robots[robot] = {
            "final_state": progress.mission_state.get(robot, "?"),
            "clouds_inserted": progress.clouds_inserted.get(robot, 0),
            "clouds_superseded": progress.clouds_superseded.get(robot, 0),
            "clouds_dropped": progress.clouds_dropped.get(robot, 0),
            "voxels_contributed": progress.voxels_contributed.get(robot, 0),
            "path_m": round(length, 2),
            "map_age_s": progress.map_age_s.get(robot, math.nan),
        }
    return {
        "robots": robots,
        "profile": fleet.profile.name,
        "link": result.link,
        "host_split": getattr(result, "host_split", "not recorded"),
        "video_source": getattr(result, "video_source", "not recorded"),
        "link_capacity": getattr(result, "link_capacity", "not recorded"),
        "ended_by": result.ended_by,
        "elapsed_s": result.elapsed_s,
        "wall_time_s": wall_time_s,
        "events": [[e.time_s, e.label, e.what] for e in result.events],
        "restarts": dict(result.restarts),
        "reserve_fraction": fleet.link.reserve_fraction,
    }


def read_mission_summary(out):
    """mission.json; for a folder written before it, what report.md's header says (labelled)."""
    path = os.path.join(out, MISSION_JSON)
    if os.path.exists(path):
        with open(path) as stream:
            return json.load(stream)
    return summary_from_report(os.path.join(out, "report.md"))


def summary_from_report(report_path):
    """A mission summary read back from an older report.md (before mission.json): its header lines,
    its Robots table and its supervisor events; {} without a report."""
    import re

    if not os.path.exists(report_path):
        return {}
    text = open(report_path).read()

    def line(name):
        match = re.search(rf"^- {name}: (.+)$", text, re.M)
        return match.group(1).strip() if match else "not recorded"

    ended = re.search(r"^- ended by: (\S+) after (\d+) s of mission \((\d+) s wall time", text, re.M)
    robots = {}
    for match in re.finditer(
        r"^\| (\w+) \| (\w+) \| (\d+) \| (\d+) \| (\d+) \| ([\d.]+) \| ([\d.naninf]+) \|$", text, re.M
    ):
        name, state, inserted, dropped, voxels, path_m, age = match.groups()
        robots[name] = {
            "final_state": state,
            "clouds_inserted": int(inserted),
            "clouds_superseded": None,  # not shown by reports before the ledger
            "clouds_dropped": int(dropped),
            "voxels_contributed": int(voxels),
            "path_m": float(path_m),
            "map_age_s": float(age),
        }
    profile = re.search(r"^- robots: .+; profile: (\w+)$", text, re.M)
    events = [
        [float(m.group(1)), m.group(2), m.group(3)]
        for m in re.finditer(r"^- (\d+) s ([^:]+): (.+)$", text.split("## Supervisor events")[-1].split("##")[0], re.M)
    ]
    return {
        "robots": robots,
        "profile": profile.group(1) if profile else "not recorded",
        "link": line("link"),
        "host_split": line("host split"),
        "video_source": line("video"),
        "link_capacity": line("link capacity"),
        "ended_by": ended.group(1) if ended else "not recorded",
        "elapsed_s": float(ended.group(2)) if ended else math.nan,
        "wall_time_s": float(ended.group(3)) if ended else math.nan,
        "events": events,
        "restarts": {},
        "read_from": "report.md (written before mission.json)",
    }


def write_mission_report(result, mission_args, wall_time_s):
    """Score the map, write mission.json, then the report (report.md, verdict.json, plots) into
    result.out_dir from its files."""
    from cps_experiments.topdown_map import plot_topdown
    from cps_fleet.fleet import load_fleet, robot_names_arg

    out = result.out_dir
    fleet = load_fleet(mission_args.fleet, profile=mission_args.profile)
    fleet = robot_names_arg(fleet, mission_args.robots.split(",") if mission_args.robots else None)
    with open(os.path.join(out, MISSION_JSON), "w") as stream:
        json.dump(mission_summary(result, fleet, wall_time_s), stream, indent=1)
    progress = result.progress
    write_trajectories(os.path.join(out, TRAJECTORIES_CSV), progress.trajectories)
    if result.map_file and os.path.exists(result.map_file):
        score, fused = score_saved_map(
            result.map_file, fleet, os.path.join(out, "ground_truth.npz"), progress.trajectories
        )
        with open(os.path.join(out, "scores.json"), "w") as stream:
            json.dump(score.as_dict(), stream, indent=2)
        plot_topdown(fused.occupied_centers(), progress.trajectories, fleet, os.path.join(out, "topdown.png"))
    # `make demo --map-f1-floor(-exact)` sets them on the mission's arguments; else the code defaults.
    return write_report(
        out, fleet, getattr(mission_args, "map_f1_floor", None), getattr(mission_args, "map_f1_floor_exact", None)
    )


def write_report(out, fleet, f1_floor=None, f1_floor_exact=None):
    """report.md, verdict.json and link.png of the mission folder `out`, from its files alone (and
    mission.json); `fleet`: the mission's (its robots and link)."""
    from cps_experiments.ledger import read_counter_series, read_ledger
    from cps_experiments.link_report import section as link_events_section
    from cps_experiments.verdict import DEMO_FILES, MAP_F1_FLOOR_WITHIN_1_VOXEL, checks_table, judge, write_verdict

    summary = read_mission_summary(out)
    stats_rows = read_csv(os.path.join(out, "stats.csv"))
    allocation_rows = read_csv(os.path.join(out, "allocation.csv"))
    event_rows = read_csv(os.path.join(out, "link_events.csv"))
    budgets = [csv_float(r["budget_mbytes_per_s"]) for r in allocation_rows]
    # The manager's own budget at the end (with --link: from iperf3's measurement), else fleet.yaml's.
    budget = budgets[-1] if budgets and math.isfinite(budgets[-1]) else fleet.link.budget_mbytes_per_s
    ended = summary.get("ended_by", "not recorded")
    lines = [
        "# Mission report",
        "",
        f"- robots: {', '.join(fleet.robot_names)}; profile: {summary.get('profile', fleet.profile.name)}",
        f"- link: {summary.get('link', 'not recorded')}",
        f"- host split: {summary.get('host_split', 'not recorded')}",
        f"- video: {summary.get('video_source', 'not recorded')}",
        f"- link capacity: {summary.get('link_capacity', 'not recorded')}",
        f"- ended by: {ended} after {summary.get('elapsed_s', math.nan):.0f} s of mission "
        f"({summary.get('wall_time_s', math.nan):.0f} s wall time including start-up and this report)",
        "",
    ]
    if summary.get("read_from"):
        lines[-1:-1] = [f"- note: these lines are read from {summary['read_from']}; judged again from the files"]

    rows = []
    for robot in fleet.robot_names:
        r = summary.get("robots", {}).get(robot, {})
        superseded = r.get("clouds_superseded")
        rows.append(
            (
                robot,
                r.get("final_state", "?"),
                r.get("clouds_inserted", "-"),
                "not recorded" if superseded is None else superseded,
                r.get("clouds_dropped", "-"),
                r.get("voxels_contributed", "-"),
                f"{r.get('path_m', math.nan):.1f}",
                f"{r.get('map_age_s', math.nan):.2f}",
            )
        )
    lines += [
        "## Robots",
        "",
        "From the map server's live statistics at the end of the mission. *Superseded*: replaced in the robot's "
        "one-cloud slot by a newer cloud of the same robot before it was inserted (not inserted; the newer one "
        "was). *Dropped*: by the map server, with no transform at the cloud's stamp, an invalid cloud or a full "
        "queue. Every other loss on the way is in the cloud ledger below.",
        "",
        markdown_table(
            (
                "robot",
                "final state",
                "clouds inserted",
                "superseded",
                "dropped by the map server",
                "occupied voxels last updated",
                "path m",
                "map age s",
            ),
            rows,
        ),
        "",
    ]
    lines += read_ledger(out, fleet.robot_names).markdown()

    scores_path = os.path.join(out, "scores.json")
    if os.path.exists(scores_path):
        from cps_mapping.scoring import read_scores

        with open(scores_path) as stream:
            scores = read_scores(json.load(stream))
        lines += [
            "## Map quality against the simulator's ground truth",
            "",
            f"Map `map.bt` ({scores.get('map_voxels')} occupied voxels at {scores.get('resolution_m')} m) against "
            f"{scores.get('truth_voxels')} ground-truth voxels ({scores.get('observable_voxels')} on the observable "
            f"surface, {observable_text(scores.get('observable_from'))}):",
            "",
            *scores_table(scores),
            "",
        ]
        if os.path.exists(os.path.join(out, "topdown.png")):
            lines += ["![top-down view of the fused map with the trajectories](topdown.png)", ""]
    else:
        lines += ["## Map quality", "", "No map was saved: see the map server's log in `logs/`.", ""]

    times, totals = managed_link_windows(stats_rows)
    busy = totals[totals > 0]
    latency = latency_summary(stats_rows)
    split = latency_split(
        read_csv(os.path.join(out, "physical_arrivals.csv")), read_csv(os.path.join(out, "arrivals.csv"))
    )
    from cps_experiments import judge as J

    phase_list = J.phases(event_rows, float(times[-1]) if len(times) else 0.0)
    capacity = J.capacity_in_force(phase_list)
    over_capacity = [t for t, v in zip(times, totals) if phase_list and v > capacity(t) / 8.0]
    reserve = summary.get("reserve_fraction", fleet.link.reserve_fraction)
    lines += [
        "## Link",
        "",
        f"Managed traffic (every robot's clouds and video) received at the digital twin in topic_stats' "
        f"{STATS_WINDOW_S:g} s sliding windows, one every second: avg {np.mean(busy) if len(busy) else 0:.3f} MB/s, "
        f"max {np.max(busy) if len(busy) else 0:.3f} MB/s, std {np.std(busy) if len(busy) else 0:.3f} MB/s. "
        + (
            f"Against the capacity the scenario set ({', '.join(f'{p.capacity_mbps:g}' for p in phase_list)} Mbit/s "
            f"in turn): {len(over_capacity)} of {len(totals)} windows above it (delivered traffic, behind the shaper). "
            if phase_list
            else ""
        )
        + f"The manager's budget at the end: {budget:.2f} MB/s ({100 * (1 - reserve):.0f} % of what it took the link "
        "to carry; the verdict judges it against the capacity in force, after every step).",
        "",
        "Latency is receive time at the digital twin minus the capture stamp (windowed: avg, max, p95 "
        "over the statistics windows). The split is per cloud, over the clouds that reached the twin, "
        "joined by capture stamp with their arrival on the robots' side: the robot side (capture to the "
        "voxel-filtered cloud on the physical host: the simulated sensor's render time and the machine's "
        "load) and the rest (encoding, rate limiting, the link and the relay).",
        "",
        markdown_table(
            (
                "robot",
                "capture → twin avg ms",
                "max ms",
                "p95 ms",
                "clouds joined",
                "of those: capture → twin avg ms",
                "robot side avg ms",
                "tissue + link avg ms",
            ),
            [
                (
                    r,
                    f"{v['avg_ms']:.1f}",
                    f"{v['max_ms']:.1f}",
                    f"{v['p95_ms']:.1f}",
                    *(
                        (
                            split[r]["clouds"],
                            f"{split[r]['total_avg_ms']:.1f}",
                            f"{split[r]['robot_side_avg_ms']:.1f}",
                            f"{split[r]['tissue_link_avg_ms']:.1f}",
                        )
                        if r in split
                        else ("0", "-", "-", "-")
                    ),
                )
                for r, v in sorted(latency.items())
            ],
        ),
        "",
    ]
    if stats_rows or allocation_rows:
        plot_link(stats_rows, allocation_rows, budget, os.path.join(out, "link.png"))
        lines += ["![bandwidth, allocated rates and latency](link.png)", ""]

    lines += link_events_section(
        event_rows,
        read_csv(os.path.join(out, "link_state.csv")),
        allocation_rows,
        times,
        totals,
        read_counter_series(out),
        read_csv(os.path.join(out, "link_estimate.csv")),
    )
    lines += ["## Supervisor events", ""]
    lines += [f"- {t:.0f} s {label}: {what}" for t, label, what in summary.get("events", [])] or ["- none"]
    if summary.get("restarts"):
        lines += [f"- restarts: {', '.join(f'{k} ×{v}' for k, v in summary['restarts'].items())}"]
    lines.append("")
    if os.path.exists(os.path.join(out, "gui.png")):
        lines += ["## Operator GUI during the mission", "", "![GUI screenshot](gui.png)", ""]
    lines += [
        "## Files",
        "",
        "`map.bt` (OctoMap, opens with octomap's tools), `ground_truth.npz`, `scores.json`, "
        "`trajectories.csv` (each robot's recorded positions), `map_age.csv` (each robot's map age, inserted and "
        "as published, and the map server's counters, as it published them), `verdict.json`, `mission.json` (what "
        "the supervisor knew), `stats.csv` (topic statistics at the twin), `physical_stats.csv` (at the robots), "
        "`arrivals.csv` and `physical_arrivals.csv` (per-cloud stamps and receive times there), `counters.csv` and "
        "`physical_counters.csv` (each node's cloud ledger counters), `allocation.csv` (bandwidth manager), "
        "`link.png`, `topdown.png`, `gui.png`, `logs/` (every node's output).",
    ]
    verdict = judge(
        out,
        DEMO_FILES,
        ended_by=None if ended == "not recorded" else ended,
        f1_floor_within_1_voxel=MAP_F1_FLOOR_WITHIN_1_VOXEL if f1_floor is None else f1_floor,
        f1_floor_exact=f1_floor_exact,
        robots=fleet.robot_names,
    )
    write_verdict(out, verdict)
    lines[2:2] = verdict.lines() + ["### Every check", "", *checks_table(verdict), ""]
    path = os.path.join(out, "report.md")
    with open(path, "w") as stream:
        stream.write("\n".join(lines) + "\n")
    return path


def scores_table(scores):
    """Report lines of a scores.json: precision, recall, F1 voxel for voxel and within ±1 voxel, coverage."""
    rows = [
        (name, *(f"{scores.get(f'{k}_{suffix}', math.nan):.3f}" for k in ("precision", "recall", "f1")))
        for name, suffix in (("voxel for voxel", "exact"), ("within ±1 voxel", "within_1_voxel"))
    ]
    return [
        markdown_table(("match", "precision", "recall", "F1"), rows),
        "",
        f"Coverage of the observable surface (within ±1 voxel): {scores.get('coverage_within_1_voxel', math.nan):.3f}.",
    ]


def rejudge(folder, fleet_file=None, f1_floor=None):
    """Write a committed mission's report and verdict again from its folder, with today's judge."""
    from cps_fleet.fleet import load_fleet

    summary = read_mission_summary(folder)
    if not os.path.exists(os.path.join(folder, MISSION_JSON)) and summary:
        # Kept, so that the report written below (in today's format) is not what is read next time.
        with open(os.path.join(folder, MISSION_JSON), "w") as stream:
            json.dump(summary, stream, indent=1)
    fleet = load_fleet(fleet_file, profile=summary.get("profile") if summary.get("profile") != "not recorded" else None)
    robots = list(summary.get("robots", {})) or None
    if robots:
        fleet = fleet.with_robots(robots)
    return write_report(folder, fleet, f1_floor)


if __name__ == "__main__":
    import sys

    for folder in sys.argv[1:]:
        print(rejudge(folder))
