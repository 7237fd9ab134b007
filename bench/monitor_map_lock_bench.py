#!/usr/bin/env python3
"""What a monitoring mission's map server does under its map lock, against a plain mission's
(issue 39's additions, measured so that they stay off the insertion path).

A monitoring mission's map keeps when each voxel was first seen (`first_seen_stamps`: the kernel
writes a stamp into a voxel the first time a ray reaches it) and its change detection reads a copy
of the map every detection period. Measured on the same rendered cloud stream (the four robots
along their routes, as bench/mapping_bench.py renders it), in one run:

1. insertion, per cloud (CPU time of `insert_batch`, the work done under the map lock): plain map
   against one keeping first-seen stamps; the two maps run interleaved, cloud by cloud;
2. what change detection holds the lock for, on the filled map: the copy main's map server took
   (`FrozenMap(map)`: the occupied and ever-hit scans and the log-odds box, under the lock) against
   the one it takes now (`map.frozen_copy()`, the grid's arrays, with the stamps; the scans run on
   the copy after the lock is released);
3. the publisher's and the save's copy (`frozen_copy`) with and without stamps.

Figures are medians over `--repeats`, machine-bound (2 shared cores): run under the heavy lock.

    python bench/monitor_map_lock_bench.py [--seconds 4] [--cache clouds.pkl] [--out docs/benchmarks/monitor_map_lock.md]
"""

import argparse
import os
import pickle
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mapping_bench import render_stream  # noqa: E402  (the same stream as the mapping benchmark)

from cps_mapping.change_detection import FrozenMap  # noqa: E402
from cps_mapping.fused_map import FusedLogOddsMap  # noqa: E402
from cps_mapping.log_odds_grid import warm_up  # noqa: E402


def _ms(seconds):
    return 1e3 * seconds


def timed(function, repeats):
    """Median wall time (s) of `function()` over `repeats` calls."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def insert_both(fleet, stream):
    """(plain map, stamped map, per-cloud CPU s of each): the same clouds into both, interleaved."""
    ranges = {r.name: fleet.mapping.max_range_m[r.type] for r in fleet.robots}
    maps = {
        stamped: FusedLogOddsMap.from_mapping_config(fleet.mapping, first_seen_stamps=stamped)
        for stamped in (False, True)
    }
    cpu = {False: [], True: []}
    for k, (t, robot, pts, origin, _) in enumerate(stream):
        order = (False, True) if k % 2 == 0 else (True, False)
        for stamped in order:
            start = time.thread_time()
            maps[stamped].insert_batch([(pts, origin)], max_range_m=ranges[robot], robot=robot, stamps_s=[t])
            cpu[stamped].append(time.thread_time() - start)
    return maps[False], maps[True], cpu


def report(fleet, stream, repeats):
    plain, stamped, cpu = insert_both(fleet, stream)
    voxels = int(np.prod(stamped._grid.dims))
    rows = [
        "| what (under the map lock) | plain map | first-seen stamps kept | ratio |",
        "|---|---|---|---|",
    ]
    p50 = {s: statistics.median(cpu[s]) for s in cpu}
    p95 = {s: float(np.percentile(cpu[s], 95)) for s in cpu}
    rows.append(
        f"| insertion, one cloud, CPU ms (median / p95 over {len(stream)} clouds) | "
        f"{_ms(p50[False]):.2f} / {_ms(p95[False]):.2f} | {_ms(p50[True]):.2f} / {_ms(p95[True]):.2f} | "
        f"{p50[True] / p50[False]:.2f} |"
    )
    copy_plain = timed(plain.frozen_copy, repeats)
    copy_stamped = timed(stamped.frozen_copy, repeats)
    rows.append(
        f"| `frozen_copy` (publisher, save, change detection now), ms | {_ms(copy_plain):.1f} | "
        f"{_ms(copy_stamped):.1f} | {copy_stamped / copy_plain:.2f} |"
    )
    old = timed(lambda: FrozenMap(stamped), repeats)
    rows.append(
        f"| change detection's copy before (`FrozenMap(map)` under the lock), ms | - | {_ms(old):.1f} | "
        f"now {_ms(copy_stamped):.1f} ms: {copy_stamped / old:.2f} of it |"
    )
    off_lock = timed(lambda: FrozenMap(stamped.frozen_copy()), repeats) - copy_stamped
    return (
        "\n".join(rows) + f"\n\nGrid: {voxels} voxels ({'x'.join(str(d) for d in stamped._grid.dims)}), "
        f"{len(stamped.occupied_index())} occupied; {len(stream)} clouds of {len(fleet.robots)} robots. "
        f"The scans `FrozenMap` makes of the copy, now off the lock: {_ms(off_lock):.1f} ms. "
        f"Medians of {repeats} repeats."
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--profile", default="paper")
    parser.add_argument("--seconds", type=float, default=4.0, help="stream length per robot, s")
    parser.add_argument("--speed", type=float, default=0.5, help="robot speed along its route, m/s")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--cache", help="pickle of the rendered stream: read if present, else written")
    parser.add_argument("--out", help="markdown file to write the table to (printed either way)")
    args = parser.parse_args()
    if args.cache and os.path.exists(args.cache):
        with open(args.cache, "rb") as stream_file:
            fleet, stream = pickle.load(stream_file)
    else:
        fleet, stream = render_stream(args.profile, args.seconds, args.speed)
        if args.cache:
            with open(args.cache, "wb") as stream_file:
                pickle.dump((fleet, stream), stream_file)
    warm_up()
    text = report(fleet, stream, args.repeats)
    print(text)
    if args.out:
        with open(args.out, "w") as out:
            out.write(text + "\n")


if __name__ == "__main__":
    main()
