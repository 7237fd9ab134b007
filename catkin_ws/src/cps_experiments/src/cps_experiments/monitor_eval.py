"""`make monitor-eval`: monitoring missions against one baseline on site changes drawn from a seed
(cps_sim.site_change_generator), half of them with the pair of robots `make monitor` sends back and
half with the whole fleet (changes anywhere its routes see), scored on what ran: the reports the
twin published while each mission ran (precision, recall, moves paired, position error, first view
-> report from the map's stamps), with the recall over the changes the mission re-observed and over
all; the re-detection on the saved maps after each mission is a second, labelled row.

Seeds: the rules (cps_mapping.change_detection.TRUSTED_RULES) were tuned on the scenarios of
TUNING_SEEDS; a run on one of them says it is not a held-out score. SCORING_SEED is the default.

Writes into --out: scenarios/<group>/*.yaml, <scenario>/ (each mission's `make monitor` folder),
results.md, results.json (and pr_curve.png with --sweep). `--no-run` scores the missions already in
--out again.
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

from cps_experiments.judge import printed_apart
from cps_experiments.markdown import markdown_table
from cps_experiments.monitor import DEFAULT_BASELINE, DEFAULT_CHANGES_FILE, DEFAULT_ROBOTS

DEFAULT_SCENARIOS = 12
# The seeds whose scenarios the rules were tuned on (issue 25's 8 missions: seed 25; issue 39's
# thin-structure and move-pairing work: seed 39): a score on them is not held out.
TUNING_SEEDS = (25, 39)
# The seed of the next held-out evaluation (docs/results/monitor-eval/README.md): drawn after the
# last change to what runs in a mission (secrets.randbelow, 2026-12-01 02:38 UTC, after 384fa9c), its
# scenarios never looked at before they run. 17645, the one before, had its one failing mission
# traced and the move pairing changed after it, as had 45756, 51999 and 42507; 70615 had its one
# miss traced and the keyframe placement changed after it; 5077 was read miss by miss and the
# grouping rules and the generator changed after it; 3901's first four missions were read too:
# none is held out now.
SCORING_SEED = 70873
# What the issue asks of what ran (issue 39's "done when").
TARGETS = dict(precision=0.95, recall=0.95, position_error_p95_m=0.2)
# The thresholds the optional sweep varies (each point: TRUSTED_RULES with one of them changed).
SWEEP = {
    "min_cluster_voxels": (8, 16, 24, 32),
    "disappeared_min_misses": (1, 2, 3, 4, 5),
    "min_viewpoints": (0, 1, 2, 3),
    "tolerance_voxels": (1, 2, 3),
    "min_hits": (1, 2, 3, 4),
    "min_known_neighbours": (0, 4, 5, 6),
}


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    changes_path: str
    robots: str  # comma-separated
    group: str  # "pair", "whole fleet" or "default"


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="monitor-eval", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenarios", type=int, default=DEFAULT_SCENARIOS, help="drawn scenarios in all")
    parser.add_argument(
        "--whole-fleet", type=int, default=None, help="how many of them send the whole fleet (default: half)"
    )
    parser.add_argument("--seed", type=int, default=SCORING_SEED, help=f"scenario seed (default {SCORING_SEED})")
    parser.add_argument(
        "--tuning", action="store_true", help=f"allow a tuning seed ({', '.join(map(str, TUNING_SEEDS))})"
    )
    parser.add_argument("--with-default", action="store_true", help="also run the default changes file")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE)
    parser.add_argument("--out", default="out/monitor-eval")
    parser.add_argument("--robots", default=DEFAULT_ROBOTS, help=f"the pair's robots (default {DEFAULT_ROBOTS})")
    parser.add_argument("--link", default="auto")
    parser.add_argument("--duration", type=float, default=300.0, metavar="S")
    parser.add_argument("--no-run", action="store_true", help="score the missions already in --out")
    parser.add_argument("--keep-done", action="store_true", help="run only the scenarios without a report in --out")
    parser.add_argument("--sweep", action="store_true", help="also sweep the thresholds on the saved maps")
    args = parser.parse_args(argv)
    if args.scenarios < 0 or (args.scenarios == 0 and not args.with_default):
        parser.error("--scenarios must be at least 1 (or 0 with --with-default)")
    if args.whole_fleet is None:
        args.whole_fleet = args.scenarios // 2
    if not 0 <= args.whole_fleet <= args.scenarios:
        parser.error(f"--whole-fleet must be within 0..{args.scenarios}")
    if args.seed in TUNING_SEEDS and not args.tuning:
        parser.error(f"seed {args.seed} is a tuning seed (its scenarios set the rules): pass --tuning to run it anyway")
    return args


def plan_scenarios(args, site, fleet):
    """[Scenario]: the default file (if asked), then the pair's and the whole fleet's drawn scenarios."""
    import rospkg

    from cps_sim.site_change_generator import generate_scenarios

    out = []
    if args.with_default:
        default = os.path.join(rospkg.RosPack().get_path("cps_bringup"), DEFAULT_CHANGES_FILE)
        out.append(Scenario("default", default, args.robots, "default"))
    groups = (
        ("pair", args.robots.split(","), args.scenarios - args.whole_fleet),
        ("fleet", fleet.robot_names, args.whole_fleet),
    )
    for group, robots, count in groups:
        if count <= 0:
            continue
        folder = os.path.join(args.out, "scenarios", group)
        paths = generate_scenarios(site, fleet, robots, count, args.seed, folder, log=lambda _: None)
        label = "pair" if group == "pair" else "whole fleet"
        out += [Scenario(f"seed{args.seed}_{group}_{i}", p, ",".join(robots), label) for i, p in enumerate(paths)]
    return out


def _near_robot_count(result, changes, matched):
    from cps_experiments.monitor_report import near_robot

    return sum(near_robot(result, c) for j, c in enumerate(changes) if j not in matched)


def score_scenario(scenario, baseline, out_dir, fleet, maps=None, rules=None):
    """One mission's row (dict) and its MonitoringResult: what ran live, and the re-detection."""
    from cps_experiments.monitor_report import evaluate_monitoring, read_live_report
    from cps_mapping.change_scoring import score_changes

    result = evaluate_monitoring(
        baseline, os.path.join(out_dir, "map.bt"), fleet, scenario.changes_path, rules=rules, maps=maps
    )
    expected = result.expected
    live = read_live_report(out_dir)

    def part(changes, score, times=None):
        matched = {m.detected_index for m in score.matches}
        moves = [i for i, e in enumerate(expected) if e.kind == "moved"]
        return dict(
            detected=score.detected,
            matched=len(score.matches),
            precision=score.precision if score.detected else None,
            recall=score.recall if score.expected else None,
            position_errors_m=[m.position_error_m for m in score.matches],
            move_errors_m=[m.position_error_m for m in score.matches if expected[m.expected_index].kind == "moved"],
            moves_paired=sum(score.match_of_expected(i) is not None for i in moves),
            reobserved_matched=sum(
                score.match_of_expected(i) is not None for i, ok in enumerate(result.reobserved) if ok
            ),
            false=[
                dict(kind=c.kind, place_m=[round(v, 2) for v in c.place_m], voxels=c.voxels)
                for j, c in enumerate(changes)
                if j not in matched
            ],
            robot_reported=_near_robot_count(result, changes, matched),
            times_s=[times[m.detected_index] for m in score.matches] if times is not None else None,
        )

    row = dict(
        scenario=scenario.name,
        group=scenario.group,
        robots=scenario.robots,
        changes=result.changes.describe(),
        made=len(expected),
        moves_made=sum(e.kind == "moved" for e in expected),
        reobserved=sum(result.reobserved),
        not_reobserved=[
            dict(name=e.name, kind=e.kind) for e, ok in zip(expected, result.reobserved) if not ok
        ],  # fmt: skip
        coverage_missing=[
            dict(name=c.name, fraction=round(c.fraction, 3)) for c in result.coverage if c.voxels and not c.seen_again
        ],
        redetected=part(result.detected, result.score),
        live=None,
        baseline_has_poses=result.baseline_trails is not None,
    )
    if live is not None:
        row["live"] = part(live.changes, score_changes(live.changes, expected), live.times_s())
        row["live"]["withdrawn"] = live.withdrawn
    return row, result


def totals(rows, key):
    """Pooled figures of `key` ("live" or "redetected") over the rows that have it."""
    parts = [(r, r[key]) for r in rows if r.get(key) is not None]
    made = sum(r["made"] for r, _ in parts)
    detected = sum(p["detected"] for _, p in parts)
    matched = sum(p["matched"] for _, p in parts)
    reobserved = sum(r["reobserved"] for r, _ in parts)
    errors = [e for _, p in parts for e in p["position_errors_m"]]
    times = [t for _, p in parts for t in (p["times_s"] or [])]
    known = [t for t in times if t is not None]
    return dict(
        missions=len(parts),
        missing=len(rows) - len(parts),
        made=made,
        detected=detected,
        matched=matched,
        precision=matched / detected if detected else None,
        recall=matched / made if made else None,
        reobserved=reobserved,
        reobserved_matched=sum(p["reobserved_matched"] for _, p in parts),
        recall_reobserved=sum(p["reobserved_matched"] for _, p in parts) / reobserved if reobserved else None,
        moves_made=sum(r["moves_made"] for r, _ in parts),
        moves_paired=sum(p["moves_paired"] for _, p in parts),
        position_error_p95_m=float(np.percentile(errors, 95)) if errors else None,
        position_error_max_m=max(errors, default=None),
        move_error_max_m=max((e for _, p in parts for e in p["move_errors_m"]), default=None),
        robot_reported=sum(p["robot_reported"] for _, p in parts),
        times_known=len(known),
        times_unknown=len(times) - len(known),
        time_min_s=min(known, default=None),
        time_median_s=float(np.median(known)) if known else None,
        time_max_s=max(known, default=None),
        times_not_positive=sum(t <= 0 for t in known),
    )


def over_every_mission(live, rows):
    """(missions without a live report, changes made, live recall, moves made) over every mission:
    a mission that left no live report found none of its changes and paired none of its moves."""
    lost = [r for r in rows if r.get("live") is None]
    made = live["made"] + sum(r["made"] for r in lost)
    moves_made = live["moves_made"] + sum(r["moves_made"] for r in lost)
    return lost, made, (live["matched"] / made if made else None), moves_made


def verdict(live, rows, seed_held_out):
    """[(what, asked, got, met)] of issue 39's "done when" on what ran. A mission that left no live
    report reported nothing: its changes count as missed in the recall and its moves as unpaired
    (a missing value fails its check), and the missions with a live report are a check of their own."""
    whole = sum(r["group"] == "whole fleet" for r in rows)
    drawn = sum(r["group"] != "default" for r in rows)
    lost, made, recall, moves_made = over_every_mission(live, rows)

    def at_least(v, bar):
        return v is not None and v >= bar

    return [
        ("scenarios drawn from a seed not used for tuning", "≥ 12", f"{drawn}" + ("" if seed_held_out else " (a tuning seed)"),
         drawn >= 12 and seed_held_out),
        ("of them whole-fleet", "half", f"{whole}", drawn > 0 and whole * 2 >= drawn),
        ("every mission left a live report", f"{len(rows)} of {len(rows)}", f"{len(rows) - len(lost)} of {len(rows)}",
         not lost),
        ("live precision", f"≥ {TARGETS['precision']}", printed_apart(live["precision"], TARGETS["precision"]),
         at_least(live["precision"], TARGETS["precision"])),
        ("live recall", f"≥ {TARGETS['recall']}", printed_apart(recall, TARGETS["recall"]), at_least(recall, TARGETS["recall"])),
        ("moves paired (live)", "every move one change", f"{live['moves_paired']} of {moves_made}",
         live["moves_paired"] == moves_made),
        ("position error p95 (live)", f"≤ {TARGETS['position_error_p95_m']} m",
         printed_apart(live["position_error_p95_m"], TARGETS["position_error_p95_m"]),
         live["position_error_p95_m"] is not None and live["position_error_p95_m"] <= TARGETS["position_error_p95_m"]),
        ("first view → report, every one positive", "> 0 s",
         f"min {_fmt(live['time_min_s'], 1)} s; {live['times_not_positive']} not positive; {live['times_unknown']} unknown",
         live["times_not_positive"] == 0 and live["times_unknown"] == 0 and live["times_known"] > 0),
    ]  # fmt: skip


def _fmt(v, digits=2):
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def sweep(scenarios, baseline, fleets, out):
    """[(threshold, value, precision, recall)] re-detected on the saved maps, and pr_curve.png."""
    from cps_experiments.monitor_report import load_maps
    from cps_mapping.change_detection import TRUSTED_RULES

    maps = {s.name: load_maps(baseline, os.path.join(d, "map.bt"), fleets[s.name]) for s, d in scenarios}
    points = []
    for key, values in SWEEP.items():
        for value in values:
            rules = dataclasses.replace(TRUSTED_RULES, **{key: value})
            matched = detected = made = 0
            for s, d in scenarios:
                row, _ = score_scenario(s, baseline, d, fleets[s.name], maps=maps[s.name], rules=rules)
                matched += row["redetected"]["matched"]
                detected += row["redetected"]["detected"]
                made += row["made"]
            points.append(
                (key, value, matched / detected if detected else math.nan, matched / made if made else math.nan)
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
    ax.set_xlabel("recall (re-detected on the saved maps)")
    ax.set_ylabel("precision (re-detected on the saved maps)")
    ax.set_title("One threshold varied, the others at the twin's defaults")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "pr_curve.png"), dpi=110)
    plt.close(fig)
    return points


def run_mission(scenario, args, out_dir):
    """One `make monitor` mission, in a process of its own (rospy's node is process-wide)."""
    subprocess.run(
        [sys.executable, "-c", "import sys; from cps_experiments.monitor import main; sys.exit(main(sys.argv[1:]))",
         "--baseline", args.baseline, "--site-changes", scenario.changes_path, "--out", out_dir,
         "--robots", scenario.robots, "--link", args.link, "--duration", str(args.duration)],
        check=False,
    )  # fmt: skip


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
    scenarios = [(s, os.path.join(args.out, s.name)) for s in plan_scenarios(args, site, fleet)]
    wall = {}
    for scenario, out_dir in scenarios:
        if args.no_run or (args.keep_done and os.path.exists(os.path.join(out_dir, "report.md"))):
            continue
        print(f"[monitor-eval] {scenario.name} ({scenario.robots}): {scenario.changes_path}", flush=True)
        t0 = time.monotonic()
        run_mission(scenario, args, out_dir)
        wall[scenario.name] = round(time.monotonic() - t0, 1)
    fleets = {s.name: robot_names_arg(fleet, s.robots.split(",")) for s, _ in scenarios}
    rows, ran = [], []
    for scenario, out_dir in scenarios:
        if not os.path.exists(os.path.join(out_dir, "map.bt")):
            print(f"monitor-eval: {scenario.name}: no map in {out_dir}; left out", file=sys.stderr)
            continue
        row, _ = score_scenario(scenario, args.baseline, out_dir, fleets[scenario.name])
        rows.append(row)
        ran.append((scenario, out_dir))
    if not rows:
        print("monitor-eval: error: no mission to score", file=sys.stderr)
        return 2
    curve = sweep(ran, args.baseline, fleets, args.out) if args.sweep else []
    meta = dict(
        baseline=args.baseline,
        seed=args.seed,
        held_out=args.seed not in TUNING_SEEDS,
        tuning_seeds=list(TUNING_SEEDS),
        pair_robots=args.robots,
        whole_fleet_robots=",".join(fleet.robot_names),
        wall_s=wall,
    )
    write_results(args.out, rows, curve, meta)
    print(f"[monitor-eval] wrote {os.path.join(args.out, 'results.md')}")
    return 0


def _row_cells(r, key):
    p = r[key]
    if p is None:
        return ("—",) * 6
    times = [t for t in (p["times_s"] or []) if t is not None]
    return (
        p["detected"],
        p["detected"] - p["matched"],
        _fmt(p["precision"]),
        _fmt(p["recall"]),
        _fmt(max(p["position_errors_m"], default=None)),
        (f"{min(times):.0f}–{max(times):.0f}" if times else "—") if p["times_s"] is not None else "—",
    )


def write_results(out, rows, curve, meta):
    """results.md and results.json in `out`: the headline and the verdict are what ran (the live
    reports); the re-detection on the saved maps and the sweep are labelled as such."""
    live, redetected = totals(rows, "live"), totals(rows, "redetected")
    checks = verdict(live, rows, meta["held_out"])
    headline = (
        f"**What ran (the twin's live reports, {live['missions']} missions): precision {live['matched']}/"
        f"{live['detected']} = {printed_apart(live['precision'], TARGETS['precision'])}, recall {live['matched']}/"
        f"{live['made']} = {printed_apart(live['recall'], TARGETS['recall'])} (over the changes in places the "
        f"missions re-observed: {live['reobserved_matched']}/{live['reobserved']} = "
        f"{printed_apart(live['recall_reobserved'], TARGETS['recall'])}), moves paired {live['moves_paired']} of "
        f"{live['moves_made']}, position error p95 {_fmt(live['position_error_p95_m'])} m, first view → report "
        f"{_fmt(live['time_min_s'], 1)}–{_fmt(live['time_max_s'], 1)} s (median {_fmt(live['time_median_s'], 1)} s).**"
    )
    seeds = (
        f"Scenarios drawn with seed {meta['seed']}, "
        + ("not a tuning seed: a held-out score" if meta["held_out"] else "**a tuning seed: not a held-out score**")
        + f" (the rules were tuned on seeds {', '.join(map(str, meta['tuning_seeds']))})."
    )
    lines = [
        "# Monitoring evaluation (`make monitor-eval`)",
        "",
        headline,
        "",
        seeds,
        "",
        markdown_table(
            ("issue 39 asks", "", "what ran", "met"), [(w, a, g, "yes" if ok else "**no**") for w, a, g, ok in checks]
        ),
        "",
        f"- baseline: `{meta['baseline']}`"
        + (
            ""
            if all(r["baseline_has_poses"] for r in rows)
            else " (**without robot poses**: its robots are not cleaned)"
        ),
        f"- robots: the pair {meta['pair_robots']}, the whole fleet {meta['whole_fleet_robots']}",
        "- live: the changes the twin's map server reported while the mission ran and had not withdrawn at its "
        "end (map_changes.json: found in 2 consecutive 5 s detection cycles); scoring: `cps_mapping.change_scoring` "
        "(same kind; place within the item's footprint grown by 0.5 m; a move is one change, scored by the "
        "error of its displacement)",
        "- first view → report: from the stamp of the first cloud inserted into the map that saw the change's "
        "place (the map's per-voxel first-seen stamps) to the detection cycle that first reported it",
        "- re-observed: the mission saw the change's place(s) again well enough to confirm or deny it "
        "(`cps_mapping.change_coverage`); a change elsewhere cannot be reported by any rule, and the mission's "
        "report lists those places",
        "",
        "## Per mission",
        "",
        markdown_table(
            (
                "scenario",
                "robots",
                "site changes",
                "made",
                "re-observed",
                "live: detected",
                "false",
                "precision",
                "recall",
                "position error m (max)",
                "first view → report s",
                "re-detected: detected",
                "false",
                "precision",
                "recall",
            ),
            [
                (
                    r["scenario"],
                    r["group"],
                    r["changes"],
                    r["made"],
                    r["reobserved"],
                    *_row_cells(r, "live"),
                    *_row_cells(r, "redetected")[:4],
                )
                for r in rows
            ]
            + [
                (
                    "**total**",
                    f"{len(rows)} missions",
                    "",
                    live["made"],
                    live["reobserved"],
                    live["detected"],
                    live["detected"] - live["matched"],
                    printed_apart(live["precision"], TARGETS["precision"]),
                    printed_apart(live["recall"], TARGETS["recall"]),
                    f"p95 {_fmt(live['position_error_p95_m'])}",
                    f"median {_fmt(live['time_median_s'], 0)}, max {_fmt(live['time_max_s'], 0)}",
                    redetected["detected"],
                    redetected["detected"] - redetected["matched"],
                    printed_apart(redetected["precision"], TARGETS["precision"]),
                    printed_apart(redetected["recall"], TARGETS["recall"]),
                )
            ],
        ),  # fmt: skip
        "",
        "## False changes (live)",
        "",
    ]
    false_rows = [
        (r["scenario"], f["kind"], ", ".join(f"{v:.2f}" for v in f["place_m"]), f["voxels"])
        for r in rows
        if r["live"]
        for f in r["live"]["false"]
    ]
    lines += [
        markdown_table(("scenario", "kind", "place x, y m", "voxels"), false_rows) if false_rows else "None.",
        "",
        "## Changes the missions did not see again",
        "",
    ]
    unseen = [(r["scenario"], e["name"], e["kind"]) for r in rows for e in r["not_reobserved"]]
    lines += [
        markdown_table(("scenario", "item", "kind"), unseen)
        if unseen
        else "None: every change's place was re-observed.",
        "",
    ]
    if curve:
        lines += [
            "## Precision–recall over the thresholds (re-detected on the saved maps)",
            "",
            "Each point: the twin's rules with one threshold changed, all missions pooled, re-detected on the saved "
            "maps after they ran (not what the operator saw live).",
            "",
            markdown_table(("threshold", "value", "precision", "recall"), [(k, v, _fmt(p), _fmt(r)) for k, v, p, r in curve]),
            "",
            "![precision-recall](pr_curve.png)",
            "",
        ]  # fmt: skip
    if meta.get("wall_s"):
        lines += [
            "Wall time per mission (s, contended 2-core machine, each under the heavy lock): "
            + ", ".join(f"{k} {v:.0f}" for k, v in meta["wall_s"].items()),
            "",
        ]
    with open(os.path.join(out, "results.md"), "w") as stream:
        stream.write("\n".join(lines))
    with open(os.path.join(out, "results.json"), "w") as stream:
        json.dump(dict(rows=rows, live=live, redetected=redetected, verdict=checks, curve=curve, meta=meta),
                  stream, indent=1, default=str)  # fmt: skip
    print("\n".join(lines[:8]))
