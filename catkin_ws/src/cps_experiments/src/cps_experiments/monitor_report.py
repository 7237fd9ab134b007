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
# How near a robot's recorded pose a false change counts as "near a robot".
ROBOT_NEAR_M = 0.5


@dataclasses.dataclass
class MonitoringResult:
    detected: list  # cps_mapping.change_detection.Change
    expected: list  # cps_sim.site_changes.ExpectedChange
    score: object  # cps_mapping.change_scoring.ChangeScore
    current_map: object  # FusedLogOddsMap of the monitoring mission
    changes: object  # cps_sim.site_changes.SiteChanges
    sites: tuple = ()  # the site before and after the changes
    baseline_map: object = None  # FusedLogOddsMap of the baseline
    baseline_trails: object = None  # robot_bodies.RobotTrails saved with the baseline, or None
    current_trails: object = None
    evidence: str = ""  # where the new map's misses at the baseline's voxels came from


def solid_near(sites, change, margin_m=NEAR_SOLID_M):
    """What the simulator has where a detected change is: the owner of a solid (equipment, fence, wall)
    within `margin_m` of its box centre in the site before or after, or "nothing"."""
    centre = (np.asarray(change.min_m) + change.max_m) / 2
    for site in sites:
        for prim in site.primitives():
            if prim.contains(centre, margin_m)[0]:
                return prim.owner
    return "nothing"


def near_robot(result, change, margin_m=ROBOT_NEAR_M):
    """True if a change's box, grown by `margin_m`, holds a pose a robot's sensor had in either
    mission: a robot's body, or what the swept volume did not cover of it."""
    lo, hi = np.asarray(change.min_m) - margin_m, np.asarray(change.max_m) + margin_m
    for trails in (result.baseline_trails, result.current_trails):
        for trail in trails.trails.values() if trails else ():
            xyz = np.asarray([p[:3, 3] for p in trail.snapshot()[1]]).reshape(-1, 3)
            if len(xyz) and np.any(np.all((xyz >= lo) & (xyz <= hi), axis=1)):
                return True
    return False


LIVE_REPORT = "map_changes.md"  # the map server's live report in a mission's folder (cps_bringup.plan)


@dataclasses.dataclass
class SavedMaps:
    """Two missions' saved maps with what was saved beside them."""

    baseline: object  # FusedLogOddsMap
    baseline_trails: object  # robot_bodies.RobotTrails or None
    baseline_hits: object  # change_detection.VoxelLevels or None
    current: object
    current_trails: object
    current_hits: object
    current_misses: object  # VoxelLevels of the new mission's misses at the baseline's voxels, or None
    _swept: object = None

    def swept(self):
        """The volume both missions' robot bodies swept (robot_bodies.SweptVolume), built once."""
        from cps_mapping.robot_bodies import SweptVolume

        if self._swept is None:
            resolution_m = self.current.resolution_m
            self._swept = SweptVolume(resolution_m).add(self.baseline_trails).add(self.current_trails)
        return self._swept


def load_maps(baseline_path, map_path, fleet) -> SavedMaps:
    """The two maps and their sidecars: robot trails (`<map>.json`), hit levels (`<map>.hits.npz`),
    and the new mission's misses at the baseline's voxels from the map server's last detection cycle
    (`map_changes_miss_levels.npz`): a .bt holds only occupied/free."""
    from cps_mapping.baseline import load_baseline, read_map_trails
    from cps_mapping.change_detection import VoxelLevels, miss_levels_path

    misses = miss_levels_path(os.path.join(os.path.dirname(os.path.abspath(map_path)), LIVE_REPORT))
    return SavedMaps(
        load_baseline(baseline_path, fleet.mapping),
        read_map_trails(baseline_path),
        VoxelLevels.of_map(baseline_path),
        load_baseline(map_path, fleet.mapping),
        read_map_trails(map_path),
        VoxelLevels.of_map(map_path),
        VoxelLevels.load(misses) if os.path.exists(misses) else None,
    )


def evaluate_monitoring(baseline_path, map_path, fleet, changes_path, rules=None, maps=None) -> MonitoringResult:
    """Detect the changes between the two saved maps under `rules` (default: the map server's, the
    live detection's without its persistence) and score them against the simulator's."""
    from cps_fleet.site import load_site
    from cps_mapping.change_detection import TRUSTED_RULES, detect_map_changes
    from cps_mapping.change_scoring import score_changes
    from cps_sim.site_changes import expected_changes, load_site_changes

    site = load_site(fleet.site_path)
    changes = load_site_changes(changes_path, site)
    expected = expected_changes(site, changes)
    m = maps or load_maps(baseline_path, map_path, fleet)
    swept = m.swept()
    detected = detect_map_changes(
        m.baseline,
        m.current,
        rules=rules or TRUSTED_RULES,
        swept=swept,
        current_trails=m.current_trails,
        current_misses=m.current_misses,
        baseline_hits=m.baseline_hits,
        current_hits=m.current_hits,
    )
    evidence = [
        "misses: the last live detection cycle" if m.current_misses else "misses: map.bt only (occupied/free)",
        "hits: both maps" if m.baseline_hits and m.current_hits else "hits: **not saved with both maps** (not tested)",
    ]
    return MonitoringResult(
        detected,
        expected,
        score_changes(detected, expected),
        m.current,
        changes,
        (site, changes.apply(site)),
        m.baseline,
        m.baseline_trails,
        m.current_trails,
        "; ".join(evidence),
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


def change_crop_lines(result, out):
    """One crop per detected change in `out`/changes/ (cps_experiments.change_crops) and the report's
    section showing them."""
    from cps_experiments.change_crops import draw_change_crop

    if not result.detected:
        return []
    os.makedirs(os.path.join(out, "changes"), exist_ok=True)
    base, now = result.baseline_map.occupied_centers(), result.current_map.occupied_centers()
    lines = ["## Each change: baseline beside now (top-down and side, the change outlined)", ""]
    for i, c in enumerate(result.detected, 1):
        m = result.score.match_of_detected(i - 1)
        what = result.expected[m.expected_index].name if m else "false"
        name = f"changes/change_{i}.png"
        draw_change_crop(
            os.path.join(out, name), c, base, now, result.current_map.resolution_m,
            title=f"#{i} {c.kind} at ({c.centroid_m[0]:.1f}, {c.centroid_m[1]:.1f}) m: {what}",
        )  # fmt: skip
        lines += [f"![change {i}]({name})", ""]
    return lines


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
            (
                f"Robots: the baseline's robot poses ({result.baseline_trails.pose_count()}) and this mission's "
                f"({result.current_trails.pose_count() if result.current_trails else 0}) were saved with the maps; "
                "the volume the robots' bodies swept is not compared."
                if result.baseline_trails is not None
                else "**The baseline has no robot poses** (saved before they were kept, or by another tool): "
                "robots it saw cannot be told from the site and may come out as disappeared changes."
            ),
            f"Evidence saved with the maps: {result.evidence}.",
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
                        else f"— (false; the site has {solid_near(result.sites, c)} there"
                        + ("; near a robot's path)" if near_robot(result, c) else ")"),
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
        lines += change_crop_lines(result, out)
    if os.path.exists(os.path.join(out, "gui.png")):
        lines += ["## Operator GUI during the mission", "", "![GUI screenshot](gui.png)", ""]
    from cps_experiments.ledger import read_ledger

    lines += read_ledger(out, fleet.robot_names).markdown()
    lines += ["## Supervisor events", ""]
    lines += [f"- {e.time_s:.0f} s {e.label}: {e.what}" for e in mission.events] or ["- none"]
    lines += [
        "",
        "## Files",
        "",
        "`map.bt` (the new map), `map_changes.md`/`.json` (the twin's last live "
        "detection), `changes.json` (this report's figures), `topdown.png`, `gui.png`, `logs/`.",
    ]
    from cps_experiments.verdict import MONITOR_FILES, checks_table, judge, write_verdict

    # The new map is judged by its change detection above, not against the ground truth: no F1 floor.
    verdict = judge(
        out, MONITOR_FILES, ended_by=mission.ended_by, f1_floor_within_1_voxel=None, robots=fleet.robot_names
    )
    write_verdict(out, verdict)
    lines[2:2] = verdict.lines() + ["### Every check", "", *checks_table(verdict), ""]
    path = os.path.join(out, "report.md")
    with open(path, "w") as stream:
        stream.write("\n".join(lines) + "\n")
    return path
