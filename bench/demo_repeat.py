#!/usr/bin/env python3
"""`make demo` N times from one checkout: each run's verdict and any freeze, in one table (issue 38).

Each run is the demo exactly as `make demo` runs it (`nodes/demo`, the default fleet and link
scenario), in its own folder under `--out`. A run *froze* if the demo did not end by itself within
`--timeout-s` (killed), if it wrote no verdict, if the verdict found a robot's published map
(what the operator sees) staler than its 3 s bar for longer than `FREEZE_S`, outside link outages
as the verdict judges it (a map standing still while the link is cut is the cut, not a freeze), or
if the twin's bridge held the link down for longer than `FREEZE_S` while the scenario had it up
(a link that never came back). Every run's verdict and reasons are listed as the report wrote them
(or, with --rejudge, as today's verdict judges the same files); nothing is averaged away.

    python bench/demo_repeat.py [--runs 10] [--out out/demo_repeat] [--results docs/results/demo_repeat.md]
    python bench/demo_repeat.py --judge-only [--rejudge] --out out/demo_repeat

Machine-bound (2 cores); run it alone, under the heavy lock.
"""

import argparse
import json
import math
import os
import re
import subprocess
import sys
import time

from cps_experiments.run_files import read_rows
from cps_experiments.verdict import judge, read_verdict, write_verdict

ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
DEMO = os.path.join(ROOT, "catkin_ws", "src", "cps_experiments", "nodes", "demo")
# The operator's map standing still this long is a freeze (the verdict's freshness bar is 3 s).
FREEZE_S = 10.0
MAP_CHECK = "map published and fresh"  # cps_experiments.verdict's check of the published map's age
TIMEOUT_S = 900.0
RUN_FILE = "demo_repeat_run.json"  # a run's exit code and wall time, for --judge-only


def stale_episodes_s(verdict):
    """{robot: the longest episode (s) the verdict found a robot's published map staler than its bar
    (outside link outages, start-up and a done route, as the verdict judges it)}; NaN where the
    verdict could not tell (a NaN age)."""
    longest = {}
    for check in verdict.checks if verdict else []:
        if check.get("name") != MAP_CHECK or check.get("status") != "FAIL":
            continue
        match = re.search(r"up to (NaN|[\d.]+) s", check.get("detail", ""))
        age = float(match.group(1)) if match else math.nan
        robot = check.get("robot", "")
        longest[robot] = age if math.isnan(age) else max(age, longest.get(robot, 0.0))
    return longest


def link_down_outside_cuts_s(run_dir):
    """The longest time (s) the twin's bridge held the link down while the scenario had it up
    (link_state.csv against link_events.csv's cut/restore, wall clock, to the mission's end). The
    verdict leaves the bridges' outages out of the map's freshness, so a link that never came back
    after a cut (run 4 of the first ten, 2026-11-28) froze the map for 385 s unseen."""
    events, states, ages = (
        read_rows(os.path.join(run_dir, name))[0] for name in ("link_events.csv", "link_state.csv", "map_age.csv")
    )
    if not states:
        return 0.0
    end_s = max([float(r["time_s"]) for r in ages if r.get("time_s")] + [float(states[-1]["stamp_s"])])
    cuts, cut_at = [], None
    for e in events:
        if e["event"] == "cut":
            cut_at = float(e["wall_time_s"])
        elif e["event"] == "restore" and cut_at is not None:
            cuts.append((cut_at, float(e["wall_time_s"])))
            cut_at = None
    if cut_at is not None:
        cuts.append((cut_at, end_s))
    longest = 0.0
    for row, nxt in zip(states, states[1:] + [None]):
        if row["up"] != "0":
            continue
        start, stop = float(row["stamp_s"]), float(nxt["stamp_s"]) if nxt else end_s
        for cut_start, cut_stop in sorted(cuts):  # what is left of the episode outside the cuts
            if cut_stop <= start or cut_start >= stop:
                continue
            longest = max(longest, cut_start - start)
            start = max(start, cut_stop)
        longest = max(longest, stop - start)
    return longest


def run_once(run_dir, timeout_s):
    """One demo in `run_dir`; (exit code or None if killed, wall s)."""
    os.makedirs(run_dir, exist_ok=True)
    t0 = time.monotonic()
    with open(os.path.join(run_dir, "demo_console.log"), "w") as log:
        proc = subprocess.Popen([sys.executable, DEMO, "--out", run_dir], stdout=log, stderr=subprocess.STDOUT)
        try:
            code = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            code = None
    wall_s = time.monotonic() - t0
    with open(os.path.join(run_dir, RUN_FILE), "w") as stream:
        json.dump({"exit": code, "wall_s": wall_s}, stream)
    return code, wall_s


def read_run(run_dir):
    """(exit code or None if killed, wall s) that run_once wrote for `run_dir`; ('?', NaN) without it."""
    try:
        with open(os.path.join(run_dir, RUN_FILE)) as stream:
            run = json.load(stream)
        return run["exit"], float(run["wall_s"])
    except (OSError, ValueError, KeyError):
        return "?", math.nan


def rejudge(run_dir):
    """Judge `run_dir` again with today's verdict: how the mission ended from its mission.json, the
    F1 floors from the verdict it wrote; verdict.json rewritten."""
    old = read_verdict(run_dir)
    with open(os.path.join(run_dir, "mission.json")) as stream:
        ended_by = json.load(stream).get("ended_by")
    floors = {}
    if old is not None:
        floors = {"f1_floor_within_1_voxel": old.f1_floor_within_1_voxel, "f1_floor_exact": old.f1_floor_exact}
    write_verdict(run_dir, judge(run_dir, ended_by=ended_by, **floors))


def judge_run(run_dir, code, wall_s):
    """One table row: verdict, freeze and why."""
    verdict = read_verdict(run_dir)
    episodes = stale_episodes_s(verdict)
    freeze = []
    if code is None:
        freeze.append(f"did not end within the timeout (killed after {wall_s:.0f} s)")
    if verdict is None:
        freeze.append("not judged: no verdict written")
    freeze += [
        f"{r}'s published map {a:.1f} s old" if math.isfinite(a) else f"{r}'s map age unknown (NaN)"
        for r, a in episodes.items()
        if not (math.isfinite(a) and a <= FREEZE_S)
    ]
    link_down_s = link_down_outside_cuts_s(run_dir)
    if link_down_s > FREEZE_S:
        freeze.append(f"the twin's bridge held the link down {link_down_s:.0f} s while the scenario had it up")
    return {
        "status": verdict.status if verdict else "INCOMPLETE (no verdict written)",
        "exit": "killed" if code is None else str(code),
        "wall_s": wall_s,
        "longest_stale_s": max(episodes.values(), default=0.0),
        "freeze": "; ".join(freeze),
        "failures": verdict.failures if verdict else [],
    }


def table(rows):
    lines = [
        "| run | verdict | exit | wall (s) | longest stale map (s) | freeze |",
        "|---|---|---|---|---|---|",
    ]
    for i, row in enumerate(rows, 1):
        lines.append(
            f"| {i} | {row['status']} | {row['exit']} | {row['wall_s']:.0f} | {row['longest_stale_s']:.1f} | "
            f"{row['freeze'] or 'none'} |"
        )
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--out", default=os.path.join(ROOT, "out", "demo_repeat"))
    parser.add_argument("--results", default=None, help="also write the table (Markdown) here")
    parser.add_argument("--timeout-s", type=float, default=TIMEOUT_S)
    parser.add_argument(
        "--judge-only", action="store_true", help="judge the runs already in --out (exit codes and wall times unknown)"
    )
    parser.add_argument(
        "--rejudge", action="store_true", help="with --judge-only: judge each run's files again with today's verdict"
    )
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    if args.rejudge and not args.judge_only:
        parser.error("--rejudge needs --judge-only")
    rows = []
    for i in range(1, args.runs + 1):
        run_dir = os.path.join(os.path.abspath(args.out), f"run_{i:02d}")
        code, wall_s = read_run(run_dir) if args.judge_only else run_once(run_dir, args.timeout_s)
        if args.rejudge:
            rejudge(run_dir)
        rows.append(judge_run(run_dir, code, wall_s))
        print("\n".join(table(rows)[-1:]), flush=True)
    passed = sum(r["status"] == "PASS" for r in rows)
    frozen = sum(bool(r["freeze"]) for r in rows)
    lines = [
        "# `make demo` repeated (bench/demo_repeat.py)",
        "",
        f"{args.runs} demos from one checkout, one after another: **{passed} of {args.runs} PASS, "
        f"{frozen} froze** (a freeze: the demo did not end by itself, a robot's published map stood "
        f"still over {FREEZE_S:.0f} s, or the twin's bridge held the link down over {FREEZE_S:.0f} s while "
        "the scenario had it up). Machine-bound: 2 cores.",
        "",
        *table(rows),
        "",
        "## Every failing verdict's reasons",
        "",
    ]
    for i, row in enumerate(rows, 1):
        for failure in row["failures"]:
            lines.append(f"- run {i}: {failure}")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.results:
        with open(args.results, "w") as stream:
            stream.write(text)
    return 0 if passed == args.runs and not frozen else 1


if __name__ == "__main__":
    sys.exit(main())
