"""The monitoring mission's report: what changed on the site, as the twin found it (the saved map
against the baseline) and as the simulator made it (the site model + the changes file), matched:
precision, recall, each match's position error, and a top-down picture with the changes marked;
and what the mission did not see again (the baseline's equipment and areas it did not re-observe
well enough to confirm or deny a change: cps_mapping.change_coverage), with the recall over the
changes it could see and over all.
"""

import dataclasses
import json
import os

import numpy as np

from cps_experiments.markdown import markdown_table

APPEARED_COLOUR, DISAPPEARED_COLOUR, MOVED_COLOUR = "tab:green", "tab:red", "tab:blue"
COLOURS = {"appeared": APPEARED_COLOUR, "disappeared": DISAPPEARED_COLOUR, "moved": MOVED_COLOUR}
# How far around an item's solids its baseline voxels are counted as its own (one voxel).
ITEM_MARGIN_M = 0.1


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
    coverage: list = ()  # cps_mapping.change_coverage.Coverage of each item and area of the baseline's site
    reobserved: tuple = ()  # per expected change: did the mission see its place(s) again

    def recall_reobserved(self):
        """(matched, made) over the changes in places the mission re-observed."""
        seen = [i for i, ok in enumerate(self.reobserved) if ok]
        return sum(self.score.match_of_expected(i) is not None for i in seen), len(seen)


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
class LiveReport:
    """What the twin reported while the mission ran (its last live report, map_changes.json): the
    changes it reported and did not withdraw, and when (the map server's clock)."""

    changes: list  # cps_mapping.change_detection.Change
    reported_s: list  # when each was first reported
    first_view_s: list  # the stamp of the first cloud that saw each one's place (None: not known)
    withdrawn: int  # reported once, withdrawn by a later cycle

    def times_s(self):
        """First view -> report (s) of each change, None where its first view is not known."""
        return [None if v is None else r - v for r, v in zip(self.reported_s, self.first_view_s)]


def read_live_report(out_dir):
    """The mission's LiveReport, or None if the map server wrote none, or none that can be read (an
    empty file: written while the mission ended, before the writes were atomic)."""
    from cps_mapping.change_detection import Change

    path = os.path.join(out_dir, LIVE_REPORT.rsplit(".", 1)[0] + ".json")
    if not os.path.exists(path):
        return None
    try:
        with open(path) as stream:
            rows = json.load(stream)
    except ValueError:
        return None
    kept = [r for r in rows if not r.get("withdrawn") and r.get("reported_s") is not None]
    return LiveReport(
        [Change.from_dict(r) for r in kept],
        [r["reported_s"] for r in kept],
        [r.get("first_view_s") for r in kept],
        sum(bool(r.get("withdrawn")) for r in rows),
    )


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
    baseline_views: object = None  # sensor_views.SensorViews saved with the baseline, or None
    current_views: object = None
    baseline_ever_hit: object = None  # voxel indices each mission's robots ever hit, or None
    current_ever_hit: object = None
    _swept: object = None

    def swept(self):
        """The volume both missions' robot bodies swept (robot_bodies.SweptVolume), built once."""
        from cps_mapping.robot_bodies import SweptVolume

        if self._swept is None:
            resolution_m = self.current.resolution_m
            self._swept = SweptVolume(resolution_m).add(self.baseline_trails).add(self.current_trails)
        return self._swept


def load_maps(baseline_path, map_path, fleet) -> SavedMaps:
    """The two maps and their sidecars: robot trails and sensor views (`<map>.json`), hit levels
    and ever-hit voxels (`<map>.hits.npz`), and the new mission's misses at the baseline's voxels
    from the map server's last detection cycle (`map_changes_miss_levels.npz`): a .bt holds only
    occupied/free."""
    from cps_mapping.baseline import load_baseline, read_map_trails, read_map_views
    from cps_mapping.change_detection import VoxelLevels, miss_levels_path, read_ever_hit

    misses = miss_levels_path(os.path.join(os.path.dirname(os.path.abspath(map_path)), LIVE_REPORT))
    return SavedMaps(
        load_baseline(baseline_path, fleet.mapping),
        read_map_trails(baseline_path),
        VoxelLevels.of_map(baseline_path),
        load_baseline(map_path, fleet.mapping),
        read_map_trails(map_path),
        VoxelLevels.of_map(map_path),
        VoxelLevels.load(misses) if os.path.exists(misses) else None,
        read_map_views(baseline_path),
        read_map_views(map_path),
        read_ever_hit(baseline_path),
        read_ever_hit(map_path),
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
    rules = rules or TRUSTED_RULES
    detected = detect_map_changes(
        m.baseline,
        m.current,
        rules=rules,
        swept=swept,
        current_trails=m.current_trails,
        baseline_trails=m.baseline_trails,
        current_views=m.current_views,
        baseline_views=m.baseline_views,
        baseline_ever_hit=m.baseline_ever_hit,
        current_ever_hit=m.current_ever_hit,
        current_misses=m.current_misses,
        baseline_hits=m.baseline_hits,
        current_hits=m.current_hits,
    )
    evidence = [
        "misses: the last live detection cycle" if m.current_misses else "misses: map.bt only (occupied/free)",
        "hits: both maps" if m.baseline_hits and m.current_hits else "hits: **not saved with both maps** (not tested)",
        "voxels ever hit: both maps"
        if m.baseline_ever_hit is not None and m.current_ever_hit is not None
        else "voxels ever hit: **not saved with both maps** (not tested)",
        "viewpoints: the inserted clouds' (with their fields of view)"
        if m.current_views is not None
        else "viewpoints: **every pose of the robots' trails** (the sensor views were not saved)",
    ]
    coverage, reobserved = site_coverage(m, site, changes, expected, rules, swept)
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
        coverage,
        reobserved,
    )


def _holds(primitives, margin_m=ITEM_MARGIN_M):
    """points -> mask: inside any of `primitives` grown by `margin_m`."""

    def holds(points):
        mask = np.zeros(len(points), dtype=bool)
        for prim in primitives:
            mask |= prim.contains(points, margin_m)
        return mask

    return holds


def _in_area(area, margin_m=0.2):
    x0, y0, x1, y1 = area.rectangle
    return lambda p: (
        (p[:, 0] >= x0 - margin_m)
        & (p[:, 0] <= x1 + margin_m)
        & (p[:, 1] >= y0 - margin_m)
        & (p[:, 1] <= y1 + margin_m)
    )


def site_coverage(maps, site, changes, expected, rules, swept):
    """([Coverage] of each item and fenced area of the baseline's site, then the rest of the hall),
    and per expected change whether the mission saw its place(s) again: an item gone or moved from
    a place re-observed (cps_mapping.change_coverage), an item new or moved to a place the mission
    saw it at (at least `min_cluster_voxels` occupied voxels of its solids in the new map) and the
    baseline had seen (at least half of those known free in the baseline)."""
    from cps_mapping.change_coverage import REOBSERVED_FRACTION, coverage, reobserved

    _, centers, seen = reobserved(maps.baseline, maps.current, rules, swept, maps.current_misses)
    regions = {item.name: _holds(item.primitives()) for item in site.equipment}
    regions.update({f"{area.name} (fenced area)": _in_area(area) for area in site.areas})
    table = coverage(centers, seen, regions, rest="the rest of the hall (walls, aisles)")
    by_name = {c.name: c for c in table}
    after = changes.apply(site)
    now = maps.current.occupied_centers()

    def seen_now(item):
        inside = now[_holds(item.primitives())(now)] if len(now) else now
        known = maps.baseline.is_free(inside, max_probability=0.5) if len(inside) else np.zeros(0, bool)
        return len(inside) >= rules.min_cluster_voxels and known.mean() >= REOBSERVED_FRACTION

    flags = []
    for e in expected:
        gone_ok = by_name[e.name].seen_again if e.kind in ("disappeared", "moved") else True
        new_ok = seen_now(after.item(e.name)) if e.kind in ("appeared", "moved") else True
        flags.append(bool(gone_ok and new_ok))
    return table, tuple(flags)


def draw_changes(ax, result: MonitoringResult):
    """The expected changes as dashed footprints, the detected ones as filled boxes with numbers."""
    from matplotlib.patches import Rectangle

    for e in result.expected:
        boxes = [(e.centroid_m, e.size_m)] + ([(e.from_centroid_m, e.from_size_m)] if e.kind == "moved" else [])
        for centre, size in boxes:
            ax.add_patch(
                Rectangle(
                    (centre[0] - size[0] / 2, centre[1] - size[1] / 2),
                    size[0],
                    size[1],
                    fill=False,
                    ec=COLOURS[e.kind],
                    ls="--",
                    lw=1.5,
                )
            )
    for i, c in enumerate(result.detected, 1):
        colour = COLOURS.get(c.kind, DISAPPEARED_COLOUR)
        ax.add_patch(Rectangle(c.min_m[:2], c.size_m[0], c.size_m[1], fc=colour, ec="k", alpha=0.55, lw=1))
        if c.from_m is not None:  # a move: an arrow from where the item stood
            ax.annotate("", c.place_m, xytext=c.from_m[:2], arrowprops=dict(arrowstyle="->", color=colour, lw=1.5))
        ax.annotate(f"{i}", c.centroid_m[:2], xytext=(6, 6), textcoords="offset points", fontsize=9, weight="bold")
    for kind, colour in COLOURS.items():
        ax.plot([], [], color=colour, lw=6, alpha=0.55, label=f"detected: {kind}")
    ax.plot([], [], color="0.3", ls="--", label="simulator's change (footprint; a move: both)")


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


def _moved_by(values):
    return f"{values[0]:+.2f}, {values[1]:+.2f}" if values is not None else "—"


def coverage_lines(result):
    """The report's section on what the mission did not see again, and the recall over what it did."""
    from cps_mapping.change_coverage import REOBSERVED_FRACTION

    score = result.score
    matched, seen = result.recall_reobserved()
    missing = [c for c in result.coverage if c.voxels and not c.seen_again]
    lines = [
        "## What this mission did not see again",
        "",
        f"A baseline voxel is re-observed when this mission saw it occupied again (within the detection's "
        f"tolerance) or saw through it often enough to call it gone; an item or area with less than "
        f"{REOBSERVED_FRACTION:.0%} of its baseline voxels re-observed cannot be confirmed or denied: "
        "a change there would be missed without a word. Send a robot there.",
        "",
    ]
    lines += [
        markdown_table(
            ("item or area", "baseline voxels", "re-observed"),
            [(c.name, c.voxels, f"{c.fraction:.0%}") for c in sorted(missing, key=lambda c: c.fraction)],
        )
        if missing
        else "Every item and area of the baseline was re-observed.",
        "",
        f"Recall over the changes in places this mission re-observed: {matched}/{seen}"
        + (f" = {matched / seen:.2f}" if seen else "")
        + f"; over all: {len(score.matches)}/{score.expected}"
        + (f" = {score.recall:.2f}" if score.expected else "")
        + ".",
        "",
    ]
    return lines


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
        from cps_mapping.change_scoring import score_changes

        live = read_live_report(out)
        live_score = score_changes(live.changes, result.expected) if live is not None else None
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
                ("", "changes detected", "changes made", "precision", "recall"),
                [
                    (what, s.detected, s.expected, f"{s.precision:.2f}", f"{s.recall:.2f}")
                    for what, s in (
                        [("**live: what the twin reported while the mission ran**", live_score)]
                        if live_score is not None
                        else []
                    )
                    + [("re-detected on the saved maps after the mission", score)]
                ],
            ),
            "",
            "A detected change is placed at the centre of its box (a surface seen from one side pulls the "
            "voxels' mean centroid toward that side) and matches a made one of the same kind whose footprint "
            "(grown by 0.5 m) holds that place; a move is one change (where the item went, and where it came "
            "from). Position error: horizontal distance from there to the centre of the item's footprint; of a "
            "move, the error of its displacement. Only places the monitoring mission saw free or occupied count "
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
                    "moved by x, y m",
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
                        _moved_by(c.displacement_m),
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
                (
                    "item",
                    "kind",
                    "centre x, y, z m",
                    "size x, y, z m",
                    "moved by x, y m",
                    "re-observed",
                    "detected as",
                    "position error m",
                ),
                [
                    (
                        e.name,
                        e.kind,
                        _xyz(e.centroid_m),
                        _xyz(e.size_m),
                        _moved_by(e.displacement_m),
                        "yes" if seen else "**no**",
                        f"#{m.detected_index + 1}" if m else "missed",
                        f"{m.position_error_m:.2f}" if m else "—",
                    )
                    for i, (e, seen) in enumerate(zip(result.expected, result.reobserved))
                    for m in [score.match_of_expected(i)]
                ],
            ),
            "",
        ]
        lines += coverage_lines(result)
        with open(os.path.join(out, "changes.json"), "w") as stream:
            json.dump(
                {
                    "detected": [dataclasses.asdict(c) for c in result.detected],
                    "expected": [dataclasses.asdict(e) for e in result.expected],
                    "score": score.as_dict(),
                    "reobserved": list(result.reobserved),
                    "coverage": [dataclasses.asdict(c) for c in result.coverage],
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
