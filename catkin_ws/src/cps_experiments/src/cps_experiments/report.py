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
    """Per stats publication (≈ 1 s apart): time and the sum of managed MB/s over all robots.

    The volume received in the window over its length (messages x mean size / window_s), not
    topic_stats' rostopic-style rate x size: a twin starved of CPU takes a backlog in one burst,
    and (n - 1) / span then reads many times what the link can carry."""
    totals = defaultdict(float)
    for row in stats_rows:
        if row.get("managed") == "True":
            messages, mean_bytes = csv_float(row.get("messages")), csv_float(row.get("mean_message_bytes"))
            value = (
                messages * mean_bytes / window_s / 1e6
                if math.isfinite(messages) and math.isfinite(mean_bytes)
                else csv_float(row["bandwidth_mbytes_per_s"])
            )
            if math.isfinite(value):
                totals[csv_float(row["time_s"])] += value
    times = sorted(totals)
    return np.array(times), np.array([totals[t] for t in times])


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


def map_quality_table(score):
    """Report lines: precision, recall, F1 voxel for voxel and within the tolerance, each row naming it."""
    from cps_mapping.scoring import tolerance_text

    rows = [
        (tolerance_text(m.tolerance_voxels), f"{m.precision:.3f}", f"{m.recall:.3f}", f"{m.f1:.3f}")
        for m in (score.exact, score.tolerant)
    ]
    return [
        markdown_table(("match", "precision", "recall", "F1"), rows),
        "",
        f"Coverage of the observable surface ({tolerance_text(score.tolerant.tolerance_voxels)}): "
        f"{score.coverage:.3f}.",
    ]


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


def write_mission_report(result, mission_args, wall_time_s):
    """Score the map, plot the link, write report.md (and scores.json) into result.out_dir."""
    from cps_experiments.topdown_map import plot_topdown
    from cps_fleet.fleet import load_fleet, robot_names_arg

    out = result.out_dir
    fleet = load_fleet(mission_args.fleet, profile=mission_args.profile)
    fleet = robot_names_arg(fleet, mission_args.robots.split(",") if mission_args.robots else None)
    stats_rows = read_csv(os.path.join(out, "stats.csv"))
    allocation_rows = read_csv(os.path.join(out, "allocation.csv"))
    budgets = [csv_float(r["budget_mbytes_per_s"]) for r in allocation_rows]
    # The manager's own budget (with --link: from iperf3's measurement), else fleet.yaml's.
    budget = budgets[-1] if budgets and math.isfinite(budgets[-1]) else fleet.link.budget_mbytes_per_s
    available_mbps = csv_float(allocation_rows[-1]["available_mbps"]) if allocation_rows else fleet.link.available_mbps

    lines = [
        "# Mission report",
        "",
        f"- robots: {', '.join(fleet.robot_names)}; profile: {fleet.profile.name}",
        f"- link: {result.link}",
        f"- host split: {getattr(result, 'host_split', 'not recorded')}",
        f"- video: {getattr(result, 'video_source', 'not recorded')}",
        f"- link capacity: {getattr(result, 'link_capacity', 'not recorded')}",
        f"- ended by: {result.ended_by} after {result.elapsed_s:.0f} s of mission "
        f"({wall_time_s:.0f} s wall time including start-up and this report)",
        "",
    ]

    progress = result.progress
    rows = []
    for robot in fleet.robot_names:
        path = np.array(progress.trajectories.get(robot) or [(math.nan,) * 3])
        length = float(np.nansum(np.linalg.norm(np.diff(path, axis=0), axis=1))) if len(path) > 1 else 0.0
        rows.append(
            (
                robot,
                progress.mission_state.get(robot, "?"),
                progress.clouds_inserted.get(robot, 0),
                progress.clouds_dropped.get(robot, 0),
                progress.voxels_contributed.get(robot, 0),
                f"{length:.1f}",
                f"{progress.map_age_s.get(robot, math.nan):.2f}",
            )
        )
    lines += [
        "## Robots",
        "",
        "From the map server's live statistics at the end of the mission. Dropped clouds are "
        "the oldest ones its bounded per-robot queues let go when insertion fell behind (or with no "
        "transform at their stamp); every one is counted.",
        "",
        markdown_table(
            (
                "robot",
                "final state",
                "clouds inserted",
                "clouds dropped",
                "occupied voxels last updated",
                "path m",
                "map age s",
            ),
            rows,
        ),
        "",
    ]

    scores = None
    write_trajectories(os.path.join(out, TRAJECTORIES_CSV), progress.trajectories)
    if result.map_file and os.path.exists(result.map_file):
        score, fused = score_saved_map(
            result.map_file, fleet, os.path.join(out, "ground_truth.npz"), progress.trajectories
        )
        scores = score.as_dict()
        with open(os.path.join(out, "scores.json"), "w") as stream:
            json.dump(scores, stream, indent=2)
        lines += [
            "## Map quality against the simulator's ground truth",
            "",
            f"Map `map.bt` ({score.map_voxels} occupied voxels at {score.resolution_m} m) against "
            f"{score.truth_voxels} ground-truth voxels ({score.observable_voxels} on the observable surface, "
            f"{observable_text(score.observable_from)}):",
            "",
            *map_quality_table(score),
            "",
        ]
        plot_topdown(fused.occupied_centers(), progress.trajectories, fleet, os.path.join(out, "topdown.png"))
        lines += ["![top-down view of the fused map with the trajectories](topdown.png)", ""]
    else:
        lines += ["## Map quality", "", "No map was saved: see the map server's log in `logs/`.", ""]

    times, totals = managed_link_windows(stats_rows)
    busy = totals[totals > 0]
    latency = latency_summary(stats_rows)
    split = latency_split(
        read_csv(os.path.join(out, "physical_arrivals.csv")), read_csv(os.path.join(out, "arrivals.csv"))
    )
    lines += [
        "## Link",
        "",
        f"Managed point-cloud traffic received at the digital twin, per ~1 s window: avg "
        f"{np.mean(busy) if len(busy) else 0:.3f} MB/s, max {np.max(busy) if len(busy) else 0:.3f} MB/s, "
        f"std {np.std(busy) if len(busy) else 0:.3f} MB/s against a budget of {budget:.2f} MB/s "
        f"({100 * (1 - fleet.link.reserve_fraction):.0f} % of {available_mbps:.1f} Mbit/s); windows over budget: "
        f"{int(np.sum(totals > budget))} of {len(totals)}.",
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

    from cps_experiments.link_report import section as link_events_section

    lines += link_events_section(
        read_csv(os.path.join(out, "link_events.csv")),
        read_csv(os.path.join(out, "link_state.csv")),
        allocation_rows,
        times,
        totals,
        read_csv(os.path.join(out, "link_estimate.csv")),
    )
    lines += ["## Supervisor events", ""]
    lines += [f"- {e.time_s:.0f} s {e.label}: {e.what}" for e in result.events] or ["- none"]
    if result.restarts:
        lines += [f"- restarts: {', '.join(f'{k} ×{v}' for k, v in result.restarts.items())}"]
    lines.append("")
    if os.path.exists(os.path.join(out, "gui.png")):
        lines += ["## Operator GUI during the mission", "", "![GUI screenshot](gui.png)", ""]
    lines += [
        "## Files",
        "",
        "`map.bt` (OctoMap, opens with octomap's tools), `ground_truth.npz`, `scores.json`, "
        "`trajectories.csv` (each robot's recorded positions), `map_age.csv` (each robot's map age as the "
        "map server published it), `verdict.json`, "
        "`stats.csv` (topic statistics at the twin), `physical_stats.csv` (at the robots), `arrivals.csv` and "
        "`physical_arrivals.csv` (per-cloud stamps and receive times there), `allocation.csv` "
        "(bandwidth manager), `link.png`, `topdown.png`, "
        "`gui.png`, `logs/` (every node's output).",
    ]
    from cps_experiments.verdict import DEMO_FILES, MAP_F1_FLOOR_WITHIN_1_VOXEL, judge, write_verdict

    # `make demo --map-f1-floor` sets map_f1_floor on the mission's arguments; else the code default.
    floor = getattr(mission_args, "map_f1_floor", None)
    verdict = judge(
        out,
        DEMO_FILES,
        ended_by=result.ended_by,
        f1_floor_within_1_voxel=MAP_F1_FLOOR_WITHIN_1_VOXEL if floor is None else floor,
    )
    write_verdict(out, verdict)
    lines[2:2] = verdict.lines()
    path = os.path.join(out, "report.md")
    with open(path, "w") as stream:
        stream.write("\n".join(lines) + "\n")
    return path
