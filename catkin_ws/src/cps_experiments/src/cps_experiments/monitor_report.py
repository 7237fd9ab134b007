"""The monitoring mission's report: what changed on the site, as the twin found it (the saved map
against the baseline) and as the simulator made it (the site model + the changes file), matched:
precision, recall, each match's position error, and a top-down picture with the changes marked.
"""

import dataclasses
import json
import os

import numpy as np

from cps_experiments.markdown import markdown_table

APPEARED_COLOUR, DISAPPEARED_COLOUR = "tab:green", "tab:red"


# How far from a false change the report looks for the solid it was made of.
NEAR_SOLID_M = 0.3


@dataclasses.dataclass
class MonitoringResult:
    detected: list  # cps_mapping.change_detection.Change
    expected: list  # cps_sim.site_changes.ExpectedChange
    score: object  # cps_mapping.change_scoring.ChangeScore
    current_map: object  # FusedLogOddsMap of the monitoring mission
    changes: object  # cps_sim.site_changes.SiteChanges
    sites: tuple = ()  # the site before and after the changes


def solid_near(sites, change, margin_m=NEAR_SOLID_M):
    """What the simulator has where a detected change is: the owner of a solid (equipment, fence, wall)
    within `margin_m` of its box centre in the site before or after, or "nothing"."""
    centre = (np.asarray(change.min_m) + change.max_m) / 2
    for site in sites:
        for prim in site.primitives():
            if prim.contains(centre, margin_m)[0]:
                return prim.owner
    return "nothing"


def evaluate_monitoring(baseline_path, map_path, fleet, changes_path) -> MonitoringResult:
    """Detect the changes between the two saved maps and score them against the simulator's."""
    from cps_fleet.site import load_site
    from cps_mapping.baseline import load_baseline
    from cps_mapping.change_detection import detect_map_changes
    from cps_mapping.change_scoring import score_changes
    from cps_mapping.map_server import MapServerOptions
    from cps_sim.site_changes import expected_changes, load_site_changes

    site = load_site(fleet.site_path)
    changes = load_site_changes(changes_path, site)
    expected = expected_changes(site, changes)
    baseline = load_baseline(baseline_path, fleet.mapping)
    current = load_baseline(map_path, fleet.mapping)
    defaults = MapServerOptions()  # what the live detection at the twin uses
    detected = detect_map_changes(
        baseline,
        current,
        tolerance_voxels=defaults.change_tolerance_voxels,
        min_cluster_voxels=defaults.change_min_cluster_voxels,
    )
    return MonitoringResult(
        detected, expected, score_changes(detected, expected), current, changes, (site, changes.apply(site))
    )


def draw_changes(ax, result: MonitoringResult):
    """The expected changes as dashed footprints, the detected ones as filled boxes with numbers."""
    from matplotlib.patches import Rectangle

    for e in result.expected:
        colour = APPEARED_COLOUR if e.kind == "appeared" else DISAPPEARED_COLOUR
        ax.add_patch(
            Rectangle(
                (e.centroid_m[0] - e.size_m[0] / 2, e.centroid_m[1] - e.size_m[1] / 2),
                e.size_m[0],
                e.size_m[1],
                fill=False,
                ec=colour,
                ls="--",
                lw=1.5,
            )
        )
    for i, c in enumerate(result.detected, 1):
        colour = APPEARED_COLOUR if c.kind == "appeared" else DISAPPEARED_COLOUR
        ax.add_patch(Rectangle(c.min_m[:2], c.size_m[0], c.size_m[1], fc=colour, ec="k", alpha=0.55, lw=1))
        ax.annotate(f"{i}", c.centroid_m[:2], xytext=(6, 6), textcoords="offset points", fontsize=9, weight="bold")
    ax.plot([], [], color=APPEARED_COLOUR, lw=6, alpha=0.55, label="detected: appeared")
    ax.plot([], [], color=DISAPPEARED_COLOUR, lw=6, alpha=0.55, label="detected: disappeared")
    ax.plot([], [], color="0.3", ls="--", label="simulator's change (footprint)")


def _xyz(values):
    return ", ".join(f"{v:.2f}" for v in values)


def write_monitor_report(mission, mission_args, wall_time_s):
    """report.md, changes.json and topdown.png in the mission's output folder; returns report.md's path."""
    from cps_experiments.topdown_map import plot_topdown
    from cps_fleet.fleet import load_fleet, robot_names_arg

    out = mission.out_dir
    fleet = load_fleet(mission_args.fleet, profile=mission_args.profile)
    fleet = robot_names_arg(fleet, mission_args.robots.split(",") if mission_args.robots else None)
    lines = [
        "# Monitoring mission report",
        "",
        f"- baseline (characterization) map: `{mission_args.baseline}`",
        f"- site changes made by the simulator: `{mission_args.site_changes}`",
        f"- robots: {', '.join(fleet.robot_names)}; link: {mission.link}",
        f"- ended by: {mission.ended_by} after {mission.elapsed_s:.0f} s of mission "
        f"({wall_time_s:.0f} s wall time including start-up and this report)",
        "",
    ]
    if not (mission.map_file and os.path.exists(mission.map_file)):
        lines += ["No map was saved: see the map server's log in `logs/`."]
    else:
        result = evaluate_monitoring(mission_args.baseline, mission.map_file, fleet, mission_args.site_changes)
        score = result.score
        lines += [
            f"Simulator: {result.changes.describe()}.",
            "",
            "## Score",
            "",
            markdown_table(
                ("changes detected", "changes made", "precision", "recall"),
                [(score.detected, score.expected, f"{score.precision:.2f}", f"{score.recall:.2f}")],
            ),
            "",
            "A detected change is placed at the centre of its box (a surface seen from one side pulls the "
            "voxels' mean centroid toward that side) and matches a made one of the same kind whose footprint "
            "(grown by 0.5 m) holds that place. Position error: horizontal distance from there to the centre "
            "of the item's footprint. Only places the monitoring mission saw free or occupied count "
            "(the free-space rule of `cps_mapping.change_detection`).",
            "",
            "## Changes the twin detected (saved map against the baseline)",
            "",
            markdown_table(
                (
                    "#",
                    "kind",
                    "centroid x, y, z m",
                    "size x, y, z m",
                    "volume m³",
                    "voxels",
                    "matches",
                    "position error m",
                ),
                [
                    (
                        i,
                        c.kind,
                        _xyz(c.centroid_m),
                        _xyz(c.size_m),
                        f"{c.volume_m3:.3f}",
                        c.voxels,
                        result.expected[m.expected_index].name
                        if m
                        else f"— (false; the site has {solid_near(result.sites, c)} there)",
                        f"{m.position_error_m:.2f}" if m else "—",
                    )
                    for i, c in enumerate(result.detected, 1)
                    for m in [score.match_of_detected(i - 1)]
                ],
            ),
            "",
            "## Changes the simulator made",
            "",
            markdown_table(
                ("item", "kind", "centre x, y, z m", "size x, y, z m", "detected as", "position error m"),
                [
                    (
                        e.name,
                        e.kind,
                        _xyz(e.centroid_m),
                        _xyz(e.size_m),
                        f"#{m.detected_index + 1}" if m else "missed",
                        f"{m.position_error_m:.2f}" if m else "—",
                    )
                    for i, e in enumerate(result.expected)
                    for m in [score.match_of_expected(i)]
                ],
            ),
            "",
        ]
        with open(os.path.join(out, "changes.json"), "w") as stream:
            json.dump(
                {
                    "detected": [dataclasses.asdict(c) for c in result.detected],
                    "expected": [dataclasses.asdict(e) for e in result.expected],
                    "score": score.as_dict(),
                },
                stream,
                indent=1,
            )
        plot_topdown(
            result.current_map.occupied_centers(),
            mission.progress.trajectories,
            fleet,
            os.path.join(out, "topdown.png"),
            overlay=lambda ax: draw_changes(ax, result),
            title="Monitoring mission: new map, detected changes (filled) and the simulator's (dashed)",
        )
        lines += ["![top-down view with the changes](topdown.png)", ""]
    if os.path.exists(os.path.join(out, "gui.png")):
        lines += ["## Operator GUI during the mission", "", "![GUI screenshot](gui.png)", ""]
    lines += ["## Supervisor events", ""]
    lines += [f"- {e.time_s:.0f} s {e.label}: {e.what}" for e in mission.events] or ["- none"]
    lines += [
        "",
        "## Files",
        "",
        "`map.bt` (the new map), `map_changes.md`/`.json` (the twin's last live "
        "detection), `changes.json` (this report's figures), `topdown.png`, `gui.png`, `logs/`.",
    ]
    from cps_experiments.verdict import MONITOR_FILES, judge, write_verdict

    # The new map is judged by its change detection above, not against the ground truth: no F1 floor.
    verdict = judge(out, MONITOR_FILES, ended_by=mission.ended_by, f1_floor_within_1_voxel=None)
    write_verdict(out, verdict)
    lines[2:2] = verdict.lines()
    path = os.path.join(out, "report.md")
    with open(path, "w") as stream:
        stream.write("\n".join(lines) + "\n")
    return path
