"""Level allocator benchmark (issue 24): `allocate_levels` for 16 robots x 2 streams (cloud, video)
x 3 levels, beside its anchor measured in the same run: the old allocator
(`allocation.allocate_frequencies`, rates only, every stream at one fixed level) on the same 32
streams. Target: median <= 5 ms per allocation (the manager allocates every 0.5 s and at once on
a selection, teleop or size change).

Four budgets (fractions of every stream at its finest level and maximum rate): "short" (some
guarantees and video floors broken, reported), "tight" (the floors and guarantees fit, rates
shared at the base levels: stages 1-2), "rich" and "richer" (every stream at its maximum and
finer levels with the rest: the knapsack, dynamic programming on its Pareto frontier).

    python bench/level_allocator_bench.py [--repeats 200] [--out docs/benchmarks/level_allocator.md] [--no-write]
"""

import argparse
import os

import numpy as np
from timing import median_max_ms

from cps_bw_manager.allocation import RobotDemand, allocate_frequencies
from cps_bw_manager.level_allocation import (
    CLOUD,
    INSPECTION_DETAIL,
    OPERATOR_VIDEO,
    VIDEO,
    StreamDemand,
    allocate_levels,
    cloud_detail_bits,
    video_detail_bits,
)
from cps_fleet.fleet import load_fleet

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
TARGET_MS = 5.0


def fleet_streams(n_robots, rng):
    """16 robots, every one with a camera; sizes the priors x U(0.5, 2); 3 inspecting, 1 selected, 1 teleop."""
    streams = load_fleet().streams
    cloud_bits = cloud_detail_bits([lvl.voxel_leaf_m for lvl in streams.cloud_levels])
    video_bits = video_detail_bits([lvl.width * lvl.height for lvl in streams.video_levels])
    demands = []
    for k in range(n_robots):
        robot = f"r{k:02d}"
        high = k in (1, 5, 9)
        operator = k in (0, 7)
        scene = rng.uniform(0.5, 2.0)
        demands.append(
            StreamDemand(
                robot,
                CLOUD,
                tuple(scene * lvl.bytes_prior for lvl in streams.cloud_levels),
                cloud_bits,
                tuple(lvl.name for lvl in streams.cloud_levels),
                weight=4.0 if high else 1.0,
                priority=int(high),
                floor_rate_hz=1.0,
                max_rate_hz=float(rng.uniform(5, 30)),
                guarantee=INSPECTION_DETAIL if high else "",
                guarantee_rate_hz=1.0,
            )
        )
        demands.append(
            StreamDemand(
                robot,
                VIDEO,
                tuple(scene * lvl.bytes_prior for lvl in streams.video_levels),
                video_bits,
                tuple(lvl.name for lvl in streams.video_levels),
                weight=4.0 if operator else 1.0,
                floor_rate_hz=streams.video_min_rate_hz,
                max_rate_hz=streams.video_max_rate_hz,
                may_go_off=True,
                guarantee=OPERATOR_VIDEO if operator else "",
                guarantee_level=streams.operator_video_level,
                guarantee_rate_hz=streams.operator_video_rate_hz,
            )
        )
    return demands


def anchor_demands(demands):
    """The old allocator's input: every stream at its middle level, rates only."""
    return [
        RobotDemand(f"{d.robot}/{d.stream}", d.level_bytes[1], d.priority, d.floor_rate_hz, d.max_rate_hz)
        for d in demands
    ]


def run(repeats):
    rng = np.random.default_rng(24)
    demands = fleet_streams(16, rng)
    anchor = anchor_demands(demands)
    everything = sum(max(d.level_bytes) * d.max_rate_hz for d in demands) / 1e6
    rows = []
    for label, fraction in (("short", 0.005), ("tight", 0.05), ("rich", 0.25), ("richer", 0.8)):
        budget = fraction * everything
        result = allocate_levels(demands, budget)
        ours = median_max_ms(lambda: allocate_levels(demands, budget), repeats, warmup=True)
        old = median_max_ms(lambda: allocate_frequencies(anchor, budget), repeats, warmup=True)
        rows.append((label, budget, result, ours, old))
    return rows


def report(rows, repeats):
    lines = [
        f"16 robots x (cloud, video) x 3 levels = 32 streams; median / max of {repeats} runs, ms.",
        "",
        "| budget | MB/s | outcome | allocate_levels | allocate_frequencies (anchor) | ours / anchor |",
        "|---|---|---|---|---|---|",
    ]
    for label, budget, result, ours, old in rows:
        if result.broken:
            outcome = f"{len(result.broken)} rules broken"
        elif result.detail_value > 0:
            outcome = f"finer levels (detail {result.detail_value:.0f})"
        else:
            outcome = "rates shared at the base levels"
        lines.append(
            f"| {label} | {budget:.2f} | {outcome} | {ours[0]:.3f} / {ours[1]:.3f} | "
            f"{old[0]:.3f} / {old[1]:.3f} | {ours[0] / old[0]:.1f}x |"
        )
    worst = max(ours[0] for _, _, _, ours, _ in rows)
    lines += [
        "",
        f"target: median <= {TARGET_MS:.0f} ms in every regime: {'met' if worst <= TARGET_MS else 'NOT met'} "
        f"(worst median {worst:.3f} ms)",
    ]
    return "\n".join(lines), worst


HEADER = """# Level allocator (issue 24)

Written by `python bench/level_allocator_bench.py`. The anchor is the old allocator
(`allocate_frequencies`: rates only, each stream at one fixed level, its middle one) on the same
32 streams in the same run: the ratio is what choosing levels costs on top of sharing rates.
Sizes: fleet.yaml's priors x U(0.5, 2) per robot; 3 robots inspecting (inspection detail), 2
with operator video; budgets as fractions of every stream at its finest level and maximum rate.

"""


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--out", default=os.path.join(ROOT, "docs", "benchmarks", "level_allocator.md"))
    parser.add_argument("--no-write", action="store_true")
    parser.add_argument("--note", default="", help="machine and load, written under the table")
    args = parser.parse_args(argv)
    text, worst = report(run(args.repeats), args.repeats)
    if args.note:
        text += f"\n\nMachine: {args.note}"
    print(text)
    if not args.no_write:
        with open(args.out, "w") as stream:
            stream.write(HEADER + text + "\n")
        print(f"\nwritten: {os.path.normpath(args.out)}")
    return 0 if worst <= TARGET_MS else 1


if __name__ == "__main__":
    raise SystemExit(main())
