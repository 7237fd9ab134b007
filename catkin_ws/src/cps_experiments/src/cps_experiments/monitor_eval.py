"""`make monitor-eval`: N monitoring missions against one baseline, on site changes the detector has
never seen (the default changes file, then N-1 scenarios drawn by cps_sim.site_change_generator
from a seed), scored per scenario and in total: precision, recall, position error, the time from
the first view of a change to its report, and whether any robot's body came out as a change. Then
the precision-recall curve over the evidence thresholds (cps_mapping.change_detection.ChangeRules),
computed again on each mission's saved maps.

Writes into --out: scenarios/*.yaml, <scenario>/ (each mission's `make monitor` folder),
results.md, results.json, pr_curve.png. `--no-run` scores missions already in --out again.
"""

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import time

import numpy as np

from cps_experiments.markdown import markdown_table
from cps_experiments.monitor import DEFAULT_BASELINE, DEFAULT_CHANGES_FILE, DEFAULT_ROBOTS

DEFAULT_SCENARIOS = 8
DEFAULT_SEED = 25
# The thresholds the curve sweeps (each point: TRUSTED_RULES with one of them changed).
SWEEP = {
    "min_cluster_voxels": (4, 8, 12, 16, 24, 32, 48),
    "disappeared_min_misses": (1, 2, 3, 4, 5),
    "min_viewpoints": (0, 1, 2, 3, 4),
    "tolerance_voxels": (0, 1, 2, 3),
    "min_hits": (1, 2, 3, 4, 5),
    "merge_gap_voxels": (0, 1, 2, 3),
    "min_known_neighbours": (0, 4, 5, 6),
}


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="monitor-eval", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--scenarios", type=int, default=DEFAULT_SCENARIOS, help="how many missions (default changes file + N-1 drawn)"
    )
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--baseline", default=DEFAULT_BASELINE)
    parser.add_argument("--out", default="out/monitor-eval")
    parser.add_argument("--robots", default=DEFAULT_ROBOTS)
    parser.add_argument("--link", default="auto")
    parser.add_argument("--duration", type=float, default=300.0, metavar="S")
    parser.add_argument("--no-run", action="store_true", help="score the missions already in --out")
    parser.add_argument("--keep-done", action="store_true", help="run only the scenarios without a report in --out")
    args = parser.parse_args(argv)
    if args.scenarios < 1:
        parser.error("--scenarios must be at least 1")
    return args


def scenario_files(args, site, fleet):
    """[(name, changes file)]: the default file, then the generated ones."""
    import rospkg

    from cps_sim.site_change_generator import generate_scenarios

    default = os.path.join(rospkg.RosPack().get_path("cps_bringup"), DEFAULT_CHANGES_FILE)
    out = [("default", default)]
    if args.scenarios > 1:
        paths = generate_scenarios(
            site, fleet, args.robots.split(","), args.scenarios - 1, args.seed, os.path.join(args.out, "scenarios")
        )
        out += [(f"seed{args.seed}_{i}", p) for i, p in enumerate(paths)]
    return out


def _place(c):
    return ((c["min_m"][0] + c["max_m"][0]) / 2, (c["min_m"][1] + c["max_m"][1]) / 2)


def first_view_s(trails, target, fleet, known_free, resolution_m, max_range_m=8.0):
    """The stamp of the first kept sensor pose of `trails` that had `target` (x, y, z) in its field
    of view (the fleet profile's depth camera: hfov and the image's aspect; lidar: its vertical
    fov), within `max_range_m` and in line of sight through the final map's known free space."""
    cam, lidar = fleet.profile.depth_camera, fleet.profile.lidar
    half_h = math.radians(cam.hfov_deg) / 2
    half_v = math.atan(math.tan(half_h) * cam.height / cam.width)
    best = math.inf
    for name, trail in trails.trails.items():
        rtype = fleet.robot_types[fleet.robot(name).type] if name in fleet.robot_names else None
        stamps, poses = trail.snapshot()
        for stamp, pose in zip(stamps, poses):
            if stamp >= best:
                break
            d = np.asarray(target) - pose[:3, 3]
            dist = float(np.linalg.norm(d))
            if dist > max_range_m or dist < 1e-6:
                continue
            local = pose[:3, :3].T @ d
            if rtype is not None and rtype.sensor == "lidar":
                if abs(math.atan2(local[2], math.hypot(local[0], local[1]))) > math.radians(lidar.vertical_fov_deg) / 2:
                    continue
            elif (
                local[2] <= 0
                or abs(math.atan2(local[0], local[2])) > half_h
                or abs(math.atan2(local[1], local[2])) > half_v
            ):
                continue
            steps = np.arange(resolution_m, dist - 0.5, resolution_m / 2)
            if len(steps) and not known_free(pose[:3, 3] + steps[:, None] * (d / dist)).all():
                continue
            best = stamp
            break
    return best


def score_scenario(name, changes_path, baseline, out_dir, fleet, maps=None, rules=None):
    """One mission's row (dict), its MonitoringResult."""
    from cps_experiments.monitor_report import evaluate_monitoring, near_robot

    result = evaluate_monitoring(baseline, os.path.join(out_dir, "map.bt"), fleet, changes_path, rules=rules, maps=maps)
    score = result.score
    errors = [m.position_error_m for m in score.matches]
    row = {
        "scenario": name,
        "changes": result.changes.describe(),
        "made": score.expected,
        "detected": score.detected,
        "matched": len(score.matches),
        "precision": score.precision,
        "recall": score.recall,
        "position_errors_m": errors,
        "false": [
            (c.kind, c.centroid_m, c.voxels, near_robot(result, c))
            for j, c in enumerate(result.detected)
            if score.match_of_detected(j) is None
        ],
        "robot_reported": sum(
            near_robot(result, c) for j, c in enumerate(result.detected) if score.match_of_detected(j) is None
        ),
    }
    return row, result


def report_times(result, out_dir, fleet):
    """Per matched expected change: seconds from its first view to its live report (map_changes.json's
    reported_s), or None when the live detection never reported it."""
    import functools

    live_path = os.path.join(out_dir, "map_changes.json")
    live = json.load(open(live_path)) if os.path.exists(live_path) else []
    known = functools.partial(result.current_map.is_free, max_probability=0.5)
    out = []
    for m in result.score.matches:
        e = result.expected[m.expected_index]
        margin = 0.5
        hits = [
            c
            for c in live
            if c["kind"] == e.kind
            and c.get("reported_s") is not None
            and all(abs(_place(c)[k] - e.centroid_m[k]) <= e.size_m[k] / 2 + margin for k in (0, 1))
        ]
        if not hits or result.current_trails is None:
            out.append(None)
            continue
        reported = min(c["reported_s"] for c in hits)
        seen = first_view_s(result.current_trails, e.centroid_m, fleet, known, result.current_map.resolution_m)
        out.append(reported - seen if math.isfinite(seen) else None)
    return out


# The twin compares every 5 s and reports a change after two detection cycles: no change can be
# reported sooner than one cycle after it was first in view; a shorter first view -> report time
# says the first-view estimate missed an earlier view.
DETECTION_CYCLE_S = 5.0


def live_score(result, out_dir):
    """(matched, detected, made) of the twin's live report (map_changes.json, what ran): each live
    change with a report matched to a made one of the same kind whose footprint (grown by 0.5 m)
    holds its place, each made change matched once; None when the live report was not kept."""
    live_path = os.path.join(out_dir, "map_changes.json")
    if not os.path.exists(live_path):
        return None
    with open(live_path) as stream:
        live = [c for c in json.load(stream) if c.get("reported_s") is not None]
    matched, used = 0, set()
    for c in live:
        for i, e in enumerate(result.expected):
            if i in used or c["kind"] != e.kind:
                continue
            if all(abs(_place(c)[k] - e.centroid_m[k]) <= e.size_m[k] / 2 + 0.5 for k in (0, 1)):
                used.add(i)
                matched += 1
                break
    return matched, len(live), len(result.expected)


def split_times(times):
    """(possible, impossible): first view -> report times, those shorter than one detection cycle
    (impossible: the first view was earlier than the estimate found) apart; None (never live) left out."""
    known = [t for t in times if t is not None]
    return [t for t in known if t >= DETECTION_CYCLE_S], [t for t in known if t < DETECTION_CYCLE_S]


def live_totals(rows):
    """The headline from what ran: the live reports' precision and recall over the missions, or, where
    a mission's live report was not kept, its recall from the matched changes the live report had
    (time_to_report_s not None) and its precision unknown (None)."""
    made = sum(r["made"] for r in rows)
    if all(r.get("live") is not None for r in rows):
        matched = sum(r["live"][0] for r in rows)
        detected = sum(r["live"][1] for r in rows)
        return dict(matched=matched, detected=detected, made=made, precision=matched / detected if detected else None,
                    recall=matched / made if made else None, source="the live reports (map_changes.json)")  # fmt: skip
    matched = sum(sum(t is not None for t in r["time_to_report_s"]) for r in rows)
    return dict(matched=matched, detected=None, made=made, precision=None, recall=matched / made if made else None,
                source="the matched changes each live report had; its false ones were not kept")  # fmt: skip


def _fmt(v, digits=2):
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def pr_curve(scenarios, baseline, fleet, out):
    """[(threshold, value, precision, recall)] over SWEEP on the saved maps, and pr_curve.png."""
    from cps_experiments.monitor_report import load_maps
    from cps_mapping.change_detection import TRUSTED_RULES

    maps = {}
    for name, path, out_dir in scenarios:
        maps[name] = load_maps(baseline, os.path.join(out_dir, "map.bt"), fleet)
    points = []
    for key, values in SWEEP.items():
        for value in values:
            rules = dataclasses.replace(TRUSTED_RULES, **{key: value})
            matched = detected = expected = 0
            for name, path, out_dir in scenarios:
                row, _ = score_scenario(name, path, baseline, out_dir, fleet, maps=maps[name], rules=rules)
                matched, detected, expected = (
                    matched + row["matched"],
                    detected + row["detected"],
                    expected + row["made"],
                )
            points.append(
                (key, value, matched / detected if detected else math.nan, matched / expected if expected else math.nan)
            )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 5))
    for key in SWEEP:
        pts = [(r, p, v) for k, v, p, r in points if k == key]
        ax.plot([r for r, _, _ in pts], [p for _, p, _ in pts], "o-", label=key)
        for r, p, v in pts:
            ax.annotate(str(v), (r, p), xytext=(3, 3), textcoords="offset points", fontsize=7)
    ax.set_xlabel("recall (all scenarios)")
    ax.set_ylabel("precision (all scenarios)")
    ax.set_title("Change detection: one threshold varied, the others at the twin's defaults")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "pr_curve.png"), dpi=110)
    plt.close(fig)
    return points


def main(argv=None):
    args = parse_args(argv)
    from cps_fleet.fleet import load_fleet, robot_names_arg
    from cps_fleet.site import load_site

    fleet = load_fleet()
    site = load_site(fleet.site_path)
    os.makedirs(args.out, exist_ok=True)
    if not os.path.isfile(args.baseline):
        print(f"monitor-eval: error: no baseline map at {args.baseline}: run `make demo` first", file=sys.stderr)
        return 2
    scenarios = [(n, p, os.path.join(args.out, n)) for n, p in scenario_files(args, site, fleet)]
    wall = {}
    for name, path, out_dir in scenarios:
        if args.no_run or (args.keep_done and os.path.exists(os.path.join(out_dir, "report.md"))):
            continue
        t0 = time.monotonic()
        print(f"[monitor-eval] {name}: {path}", flush=True)
        # One process per mission: rospy's node (the mission monitor's) is process-wide and cannot
        # move to the next mission's master.
        subprocess.run(
            [sys.executable, "-c", "import sys; from cps_experiments.monitor import main; sys.exit(main(sys.argv[1:]))",
             "--baseline", args.baseline, "--site-changes", path, "--out", out_dir, "--robots", args.robots,
             "--link", args.link, "--duration", str(args.duration)],
            check=False,
        )  # fmt: skip
        wall[name] = time.monotonic() - t0
    fleet_scored = robot_names_arg(fleet, args.robots.split(","))
    rows = []
    for name, path, out_dir in scenarios:
        if not os.path.exists(os.path.join(out_dir, "map.bt")):
            print(f"monitor-eval: {name}: no map in {out_dir}; left out", file=sys.stderr)
            continue
        row, result = score_scenario(name, path, args.baseline, out_dir, fleet_scored)
        row["time_to_report_s"] = report_times(result, out_dir, fleet_scored)
        row["live"] = live_score(result, out_dir)
        row["baseline_has_poses"] = result.baseline_trails is not None
        rows.append(row)
    if not rows:
        print("monitor-eval: error: no mission to score", file=sys.stderr)
        return 2
    curve = pr_curve(
        [s for s in scenarios if os.path.exists(os.path.join(s[2], "map.bt"))], args.baseline, fleet_scored, args.out
    )
    meta = dict(
        baseline=args.baseline,
        scenarios=args.scenarios,
        seed=args.seed,
        robots=args.robots,
        wall_s=wall,
        tuned_on="the rules (TRUSTED_RULES) were set on earlier runs of these seeds' scenarios",
    )
    write_results(args.out, rows, curve, meta)
    print(f"[monitor-eval] wrote {os.path.join(args.out, 'results.md')}")
    return 0


def write_results(out, rows, curve, meta):
    """results.md and results.json in `out` from the scored missions: the headline is what ran (the
    live reports); the saved maps' re-detection and the threshold sweep are labelled as such."""
    total = {k: sum(r[k] for r in rows) for k in ("made", "detected", "matched", "robot_reported")}
    errors = [e for r in rows for e in r["position_errors_m"]]
    times, impossible = split_times([t for r in rows for t in r["time_to_report_s"]])
    total_precision = total["matched"] / total["detected"] if total["detected"] else math.nan
    total_recall = total["matched"] / total["made"] if total["made"] else math.nan
    p95 = float(np.percentile(errors, 95)) if errors else None
    live = live_totals(rows)
    table = markdown_table(
        ("scenario", "site changes", "made", "detected", "false", "precision", "recall", "position error m (max)",
         "first view → report s (max)", "robot reported"),
        [
            (r["scenario"], r["changes"], r["made"], r["detected"], r["detected"] - r["matched"], _fmt(r["precision"]),
             _fmt(r["recall"]), _fmt(max(r["position_errors_m"], default=None)),
             _fmt(max(split_times(r["time_to_report_s"])[0], default=None), 0)
             + f" ({sum(t is None for t in r['time_to_report_s'])} never live"
             + "".join(f"; {t:.1f} impossible" for t in split_times(r["time_to_report_s"])[1]) + ")",
             r["robot_reported"])
            for r in rows
        ]
        + [("**total (re-detected on the saved maps)**", f"{len(rows)} missions", total["made"], total["detected"],
            total["detected"] - total["matched"], _fmt(total_precision), _fmt(total_recall), f"p95 {_fmt(p95)}",
            f"median {_fmt(float(np.median(times)) if times else None, 0)}, max {_fmt(max(times, default=None), 0)}"
            + (f"; {len(impossible)} impossible" if impossible else ""), total["robot_reported"])],
    )  # fmt: skip
    false_rows = [(r["scenario"], kind, ", ".join(f"{v:.2f}" for v in c), n, "yes" if robot else "no")
                  for r in rows for kind, c, n, robot in r["false"]]  # fmt: skip
    live_line = (
        f"**What ran (the live reports): recall {live['matched']}/{live['made']} = {live['recall']:.2f}, precision "
        + (
            f"{live['matched']}/{live['detected']} = {live['precision']:.2f}"
            if live["precision"] is not None
            else "not known (the live reports' false changes were not kept)"
        )
        + f"** (from {live['source']}). The table below re-detects on each mission's saved maps after it ended: "
        "not what the operator saw live."
    )
    lines = [
        "# Monitoring evaluation (`make monitor-eval`)",
        "",
        live_line,
        "",
        f"- baseline: `{meta['baseline']}`"
        + (
            ""
            if all(r["baseline_has_poses"] for r in rows)
            else " (**without robot poses**: its robots are not cleaned)"
        ),
        f"- scenarios: the default changes file, then {meta['scenarios'] - 1} drawn with seed {meta['seed']} "
        f"(cps_sim.site_change_generator; files in `scenarios/`); robots {meta['robots']}",
        "- re-detection: `cps_mapping.change_detection.TRUSTED_RULES` on the saved maps after each mission (the "
        "map server's rules; the live report also waits 2 detection cycles); scoring: `cps_mapping.change_scoring` "
        "(same kind, place within the item's footprint grown by 0.5 m)",
        "- first view → report: from the first kept sensor pose with the item's centre in its field of view, "
        "in range and in line of sight through the final map's free space, to the live report (map_changes.json); "
        f"a time under one {DETECTION_CYCLE_S:g} s detection cycle is impossible (the first view was earlier than "
        "found) and left out of the median and the maximum, listed apart",
        "",
        table,
        "",
        "## False changes",
        "",
        markdown_table(("scenario", "kind", "centroid x, y, z m", "voxels", "near a robot's path"), false_rows)
        if false_rows
        else "None.",
        "",
        "## Precision-recall over the thresholds",
        "",
        "Each point: the twin's rules with one threshold changed, all scenarios pooled, re-detected on the saved "
        f"maps. Not a held-out score: {meta.get('tuned_on', 'the rules were tuned on these scenarios')}.",
        "",
        markdown_table(
            ("threshold", "value", "precision", "recall"), [(k, v, _fmt(p), _fmt(r)) for k, v, p, r in curve]
        ),
        "",
        "![precision-recall](pr_curve.png)",
        "",
    ]
    if meta.get("wall_s"):
        lines += [
            "Wall time per mission (s, contended 2-core machine): "
            + ", ".join(f"{k} {v:.0f}" for k, v in meta["wall_s"].items()),
            "",
        ]
    with open(os.path.join(out, "results.md"), "w") as stream:
        stream.write("\n".join(lines))
    with open(os.path.join(out, "results.json"), "w") as stream:
        json.dump({"rows": rows, "total": {**total, "precision": total_precision, "recall": total_recall,
                   "position_error_p95_m": p95}, "live": live, "impossible_times_s": impossible, "curve": curve,
                   "meta": meta}, stream, indent=1, default=str)  # fmt: skip
    print("\n".join(lines[:14]))
