"""The README's figures, generated from the committed run files, each between its markers.

Every paragraph of README.md between `<!-- NAME -->` and `<!-- /NAME -->` is this module's output
for the committed files it names (SECTIONS), judged with cps_experiments.judge; a test fails when
a sentence and its file disagree, so the README never quotes a run other than the one committed
beside it, nor a figure its own file does not hold.

    python -m cps_experiments.readme_figures          # print the sections
    python -m cps_experiments.readme_figures --write  # put them into README.md
"""

import argparse
import json
import os
import re
import sys

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), *[".."] * 5))
RESULTS = os.path.join(REPO, "docs", "results")
DEMO_DIR = os.path.join(RESULTS, "demo")
README = os.path.join(REPO, "README.md")
TWIN_CAPACITY_JSON = os.path.join(REPO, "docs", "benchmarks", "twin_capacity_results.json")
START, END = "<!-- demo-figures -->", "<!-- /demo-figures -->"  # the demo's markers (the first section)


def markers(name):
    return f"<!-- {name} -->", f"<!-- /{name} -->"


def _ended_by(report_text):
    """'done after 73 s of mission (110 s wall time ...)' from the report's 'ended by' line, or ''."""
    match = re.search(r"^- ended by: (.+)$", report_text, re.M)
    return match.group(1).strip() if match else ""


def demo_paragraph(demo_dir=DEMO_DIR):
    """The README paragraph on the committed demo run in `demo_dir`."""
    with open(os.path.join(demo_dir, "verdict.json")) as stream:
        verdict = json.load(stream)
    with open(os.path.join(demo_dir, "scores.json")) as stream:
        scores = json.load(stream)
    with open(os.path.join(demo_dir, "report.md")) as stream:
        ended = _ended_by(stream.read())
    failures = verdict.get("failures", [])
    reasons = "".join(f"\n  - {reason}" for reason in failures)
    return (
        f"The committed run of `make demo` ([docs/results/demo/](docs/results/demo/report.md)), four robots "
        f"across the shaped link: {ended or 'its end not recorded'}. Its verdict is **{verdict['status']}**{':' if failures else '.'}"
        f"{reasons}\n\n"
        f"The fused map against the simulator's ground truth at {scores['resolution_m']:g} m: voxel for voxel "
        f"**F1 {scores['f1_exact']:.3f}** (precision {scores['precision_exact']:.3f}, recall "
        f"{scores['recall_exact']:.3f}); within ±1 voxel in all 26 directions, F1 "
        f"{scores['f1_within_1_voxel']:.3f} (precision {scores['precision_within_1_voxel']:.3f}, recall "
        f"{scores['recall_within_1_voxel']:.3f}); {100 * scores['coverage_within_1_voxel']:.1f} % of the observable "
        f"surface ({scores['observable_voxels']} voxels; the surface from: {scores['observable_from']}) found within ±1 voxel. "
        f"Link use, per-cloud latency, the cloud ledger and every check are in its report."
    )


def monitoring_paragraph(results_dir=RESULTS):
    """The README's monitoring sentences from `make monitor-eval`'s committed results.json: what
    ran live is the headline (the re-detection on the saved maps labelled as such), with its seed
    said to be held out or not."""
    with open(os.path.join(results_dir, "monitor-eval", "results.json")) as stream:
        results = json.load(stream)
    live, again, meta = results["live"], results["redetected"], results["meta"]
    rows = results["rows"]
    whole = sum(r["group"] == "whole fleet" for r in rows)
    unmet = [f"{what} ({got}; asked {asked})" for what, asked, got, met in results["verdict"] if not met]

    from cps_experiments.judge import printed_apart
    from cps_experiments.monitor_eval import TARGETS

    precision, recall = TARGETS["precision"], TARGETS["recall"]

    def ratio(a, b, bar):
        return f"{a}/{b} = {printed_apart(a / b, bar)}" if b else "—"

    return (
        f"Over {len(rows)} monitoring missions on site changes drawn from seed {meta['seed']} "
        + ("(not a seed the rules were tuned on)" if meta["held_out"] else "(**a seed the rules were tuned on**)")
        + f", {whole} of them with the whole fleet ([docs/results/monitor-eval/](docs/results/monitor-eval/README.md)), "
        + _live_missing(live, rows)
        + f"what the twin reported live: precision {ratio(live['matched'], live['detected'], precision)}, recall "
        f"{ratio(live['matched'], live['made'], recall)} (over the changes in places the missions re-observed "
        f"{ratio(live['reobserved_matched'], live['reobserved'], recall)}), moves paired {live['moves_paired']} of "
        f"{live['moves_made']}, position error p95 {live['position_error_p95_m']:.2f} m, first view → report "
        f"{live['time_min_s']:.1f}–{live['time_max_s']:.1f} s; re-detected on the saved maps after each mission "
        f"(not what the operator saw): precision {ratio(again['matched'], again['detected'], precision)}, recall "
        f"{ratio(again['matched'], again['made'], recall)}. "
        + (
            (
                "Every figure issue 39 asks is met"
                + (" over the missions with a live report." if live["missing"] else ".")
            )
            if not unmet
            else f"Not met: {'; '.join(unmet)}."
        )
    )


def _live_missing(live, rows):
    """'' if every mission left a live report; else how many did not, and the live recall with their
    changes counted as missed (the headline's figures are over the missions that left one)."""
    from cps_experiments.monitor_eval import over_every_mission

    if not live.get("missing"):
        return ""
    lost, made, recall, _ = over_every_mission(live, rows)
    names = ", ".join(r["scenario"] for r in lost)
    return (
        f"**{len(lost)} of them left no live report** ({names}: live figures over the other {live['missions']}; "
        f"its changes counted as missed, the recall of what ran is {live['matched']}/{made} = {recall:.2f}), "
    )


def fig13_live_paragraph(results_dir=RESULTS):
    """The README's Fig. 13 live sentences from fig13_live.csv (live_scaling.verdict's bar)."""
    from cps_experiments.live_scaling import LiveRun, measured_from_csv, verdict
    from cps_experiments.report import read_csv

    measured = measured_from_csv(read_csv(os.path.join(results_dir, "fig13_live.csv")))
    sizes = sorted({live.robots for live in measured})
    links = sorted({live.link_mbps for live in measured if live.link_mbps})
    largest, link = sizes[-1], links[-1]
    on, off = measured.get(LiveRun(largest, link, True)), measured.get(LiveRun(largest, link, False))
    held = verdict(on)
    failed = [name for name, c in held.items() if c.failed]

    def arm(f):
        window = f"{f['min_window_hz']:.1f} Hz" if f.get("windows_cover_mission") else "not recomputable"
        return (
            f"slowest robot {f['min_hz']:.2f} Hz on average (slowest 10 s window {window}), F1 "
            f"{100 * f['f1_exact_fraction']:.1f} % voxel for voxel and {100 * f['f1_fraction']:.1f} % within ±1 voxel "
            f"of the unconstrained run's, map server dropped {100 * f['dropped_fraction']:.1f} %, cloud latency p95 "
            f"{f['latency_p95_ms']:.0f} ms, teleop p95 {f['teleop_p95_ms']:.0f} ms"
        )

    return (
        "Fig. 13 run live ([fig13_live](docs/results/fig13_live.md), `experiments fig13_live`, measured): fleets of "
        f"{sizes[0]}–{largest} mixed robots on {', '.join(f'{x:g}' for x in links)} Mbit/s, manager on and off, "
        f"beside each fleet on loopback: {len(measured)} missions"
        + ("" if 10.0 in links else " (the 10 Mbit/s rows were not run)")
        + f". At {largest} robots on {link:g} Mbit/s with the manager: {arm(on)}; without: {arm(off)}. The bar "
        f"(≥ 1 Hz in every 10 s window, no window over budget, F1 ≥ 95 % both ways, ≤ 1 % dropped, teleop p95 ≤ "
        f"50 ms) is {'met' if not failed else 'not met; it fails on ' + '; '.join(failed)}."
        + newest_16_robot_sentence(os.path.join(results_dir, FIG13_LIVE_NEWEST))
    )


# The newest 16-robot runs (issue 36), newer than fig13_live.csv's sweep: the README says both.
FIG13_LIVE_NEWEST = "issue36_n16_session21"


def newest_16_robot_sentence(folder):
    """The README's sentence on the newest 16-robot runs, from their fig13_live.csv ('' without it)."""
    from cps_experiments.live_scaling import measured_from_csv, verdict
    from cps_experiments.report import read_csv

    path = os.path.join(folder, "fig13_live.csv")
    if not os.path.exists(path):
        return ""
    measured = measured_from_csv(read_csv(path))
    parts = []
    for link in sorted({live.link_mbps for live in measured if live.link_mbps}, reverse=True):
        for manager in (True, False):
            runs = sorted(
                (live for live in measured if live.link_mbps == link and live.manager == manager),
                key=lambda r: r.repeat,
            )
            if not runs:
                continue
            figures = [measured[r] for r in runs]
            held = [not any(c.failed for c in verdict(f).values()) for f in figures]
            parts.append(
                f"{link:g} Mbit/s {'with' if manager else 'without'} the manager: robots reaching the twin "
                + " / ".join(str(f["robots_reached"]) for f in figures)
                + ", slowest 10 s window "
                + " / ".join(f"{f['min_window_hz']:.1f}" for f in figures)
                + " Hz, teleop p95 "
                + " / ".join(f"{f['teleop_p95_ms']:.0f}" for f in figures)
                + f" ms, the bar met in {sum(held)} of {len(held)}"
            )
    name = os.path.basename(folder)
    return (
        f" Newer 16-robot runs ([{name}](docs/results/{name}/README.md), {len(measured)} missions, run 1 / run 2): "
        + "; ".join(parts)
        + "."
    )


def link_thesis_paragraph(results_dir=RESULTS):
    """The README's link_thesis sentences from link_thesis.csv (link_thesis.judge's bar)."""
    from cps_experiments import link_thesis as L
    from cps_experiments.report import read_csv

    rows = L.rows_from_csv(read_csv(os.path.join(results_dir, "link_thesis.csv")))
    phase = {
        (r["arm"], L.repeat_of(r)): r
        for r in rows
        if r.get("scenario") == L.JUDGED_SCENARIO
        and r.get("stream") == "link"
        and r.get("capacity_mbps") == L.JUDGED_CAPACITY_MBPS
    }
    with open(os.path.join(results_dir, L.RUNS_JSON)) as stream:
        selected = json.load(stream)["selected"]
    repeats = L.judged_repeats(rows)

    def arm(key):
        r, (name, k) = phase[key], key
        run = f" (run {k} of {len(repeats)})" if name == L.ARM_DEFAULT and len(repeats) > 1 else ""
        return (
            f"{L.ARM_SHORT[name]}{run}: offered {r['offered_mean_mbytes_per_s']:.2f} MB/s of managed streams, the "
            f"twin received {r['received_mean_mbytes_per_s']:.3f} "
            f"({r['received_mean_mbytes_per_s'] / r['offered_mean_mbytes_per_s']:.0%})"
        )

    verdicts, held, conditions = [], 0, 0
    for k in repeats:
        bar = L.judge(rows, selected, L.ARM_DEFAULT, k)
        failed, conditions = [name for name, c in bar.items() if c.failed], len(bar)
        held += not failed
        verdicts.append(f"run {k}: " + (f"{len(failed)} fail ({'; '.join(failed)})" if failed else "all held"))
    order = (L.ARM_OFF, L.ARM_ANNOUNCED, L.ARM_IPERF3, L.ARM_DEFAULT)
    return (
        f"link_thesis ([link_thesis](docs/results/link_thesis.md), measured): four robots with video on "
        f"{L.JUDGED_SCENARIO}; in its {L.JUDGED_CAPACITY_MBPS:g} Mbit/s phase "
        f"({L.JUDGED_CAPACITY_MBPS / 8:.3f} MB/s), manager "
        + "; ".join(arm(key) for key in sorted(phase, key=lambda key: (order.index(key[0]), key[1])))
        + f". The operator's bar there, in the default configuration, is held in {held} of {len(repeats)} runs "
        + f"(all {conditions} conditions in a run): {'; '.join(verdicts)}."
    )


def twin_capacity_paragraph(path=TWIN_CAPACITY_JSON):
    """The README's twin capacity sentence from the committed sweeps (bench/twin_capacity.py: issue
    37's bars, cps_experiments.twin_replay.judge_sweep)."""
    from cps_experiments.twin_replay import MAX_FALL, MAX_SUPERSEDED, judge_sweep

    with open(path) as stream:
        sweeps = json.load(stream).get("sweeps", {})
    parts = []
    for _key, sweep in sorted(sweeps.items()):
        rows = sorted(sweep["rows"], key=lambda r: r["robots"])
        verdict = judge_sweep(rows)
        last = rows[-1]
        cpus = sweep["twin_cpus"]
        parts.append(
            f"{sweep['profile']} profile on {cpus} twin CPU{'s' if cpus > 1 else ''}"
            + (f", receive process at nice {sweep['receive_nice']}" if sweep.get("receive_nice") is not None else "")
            + f": {verdict['capacity']} robots "
            f"held ({verdict['fresh_capacity']} by freshness alone, superseded not judged; N run: "
            f"{', '.join(str(r['robots']) for r in rows)}); at N = {last['robots']} "
            f"{last['inserted_clouds_per_s']:.0f} clouds/s inserted, map age p95 {last['age_p95_s']:.2f} s, worst "
            f"fall of inserted clouds/s past the capacity {100 * verdict['worst_fall']:.0f} % (no cliff: "
            f"{'holds' if verdict['no_cliff'] else 'fails'}), no robot starving: "
            f"{'holds' if verdict['no_starving'] else 'fails'}, every cloud accounted for: "
            f"{'yes' if verdict['ledger'] else 'no'}"
        )
    measured = "; ".join(parts) if parts else "no sweep committed"
    return (
        "Twin capacity ([twin_capacity](docs/benchmarks/twin_capacity.md), measured by replaying a recorded "
        f"mission as N robots into the twin alone, under the heavy lock on a shared 2-core machine): {measured}. "
        f"Held means ≤ 1 % of the clouds sent lost, ≤ {100 * MAX_SUPERSEDED:g} % superseded and every robot's map "
        f"age p95 ≤ 1 s; no cliff means inserted clouds/s never more than {100 * MAX_FALL:g} % below its highest "
        "at a smaller N."
    )


# README section name -> the function that writes it.
SECTIONS = {
    "demo-figures": demo_paragraph,
    "monitor-figures": monitoring_paragraph,
    "fig13-live-figures": fig13_live_paragraph,
    "link-thesis-figures": link_thesis_paragraph,
    "twin-capacity-figures": twin_capacity_paragraph,
}


def readme_section(readme_text, name="demo-figures"):
    """The text between a section's markers in README.md; ValueError if they are missing."""
    start, end = markers(name)
    a, b = readme_text.find(start), readme_text.find(end)
    if a < 0 or b < a:
        raise ValueError(f"README.md has no {start} ... {end} section")
    return readme_text[a + len(start) : b].strip()


def write_sections(text):
    """README text with every section replaced by what its files say."""
    for name, make in SECTIONS.items():
        readme_section(text, name)  # the markers must be there
        start, end = markers(name)
        a, b = text.find(start), text.find(end)
        text = text[: a + len(start)] + "\n" + make() + "\n" + text[b:]
    return text


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="replace the sections in README.md")
    args = parser.parse_args(argv)
    if not args.write:
        for name, make in SECTIONS.items():
            print(f"[{name}]\n{make()}\n")
        return 0
    with open(README) as stream:
        text = stream.read()
    with open(README, "w") as stream:
        stream.write(write_sections(text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
