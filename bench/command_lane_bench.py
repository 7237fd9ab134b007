#!/usr/bin/env python3
"""Benchmark of teleop latency under cloud load: the command class in its own bridge process per
side (lanes, what bringup runs) against one bridge process per side carrying every class (the
anchor, the bridge before the lanes). Two masters on loopback, no shaping; 200 kB clouds at 30 Hz
(6 MB/s) cross robots -> twin while 20 Hz teleop commands cross twin -> robots. Machine-bound:
everything shares this machine's cores.

    python bench/command_lane_bench.py [--runs 3] [--seconds 15] [--write docs/benchmarks/command_lane.md]
"""

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from cps_fleet import names
from cps_link.zenoh_session import MAKE_CERTS, bridge_argv
from cps_ros.processes import RosGraph, find_node, free_port

ROBOT = "scout"
HERE = os.path.dirname(os.path.abspath(__file__))
CLOUD_LOAD = find_node("cps_harness", "cloud_load")
TELEOP_PROBE = find_node("cps_harness", "teleop_probe")
LOAD = f"{ROBOT}:200000:30"
TELEOP_HZ = 20


def _rows(path):
    if not os.path.exists(path):
        return []
    with open(path) as stream:
        return [tuple(map(float, line.split())) for line in stream if len(line.split()) == 2]


def one_run(lanes, seconds, tmp):
    """Teleop latencies (ms) of one run, after the link is up and the load flows."""
    certs = os.path.join(tmp, "certs")
    if not os.path.exists(certs):
        subprocess.run([MAKE_CERTS, certs], check=True, capture_output=True)
    twin, robots = RosGraph(log_dir=tmp), RosGraph(log_dir=tmp)
    received = os.path.join(tmp, f"teleop_{'lanes' if lanes else 'one'}_{time.time():.0f}.txt")
    try:
        twin.start()
        robots.start()
        for lane in ("main", "command") if lanes else ("all",):
            port = free_port()
            for graph, side, name in ((twin, "twin", f"bt_{lane}"), (robots, "robots", f"br_{lane}")):
                argv = bridge_argv(
                    sys.executable, side, "127.0.0.1", [ROBOT], certs, port, lane=lane, robots_address="127.0.0.1"
                )
                graph.popen(argv, name=name)
        robots.popen(
            [
                sys.executable,
                CLOUD_LOAD,
                LOAD,
                f"{names.absolute(names.robot_topic(ROBOT, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(ROBOT))}",
            ],
            name="load",
        )
        robots.popen([sys.executable, TELEOP_PROBE, "recv", ROBOT, received], name="recv")
        twin.popen([sys.executable, TELEOP_PROBE, "send", ROBOT, str(TELEOP_HZ)], name="send")
        deadline = time.monotonic() + 60
        while not _rows(received) and time.monotonic() < deadline:
            time.sleep(0.2)
        start = len(_rows(received))
        if not start:
            raise RuntimeError("no teleop reached the robots' side within 60 s")
        time.sleep(seconds)
        rows = _rows(received)[start:]
        return [(got - sent) * 1e3 for got, sent in rows]
    finally:
        twin.close()
        robots.close()


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--write", default=None, help="also write the table to this markdown file")
    args = parser.parse_args()
    tmp = tempfile.mkdtemp(prefix="cps-lane-bench-")
    results = {"lanes": [], "one process": []}
    try:
        for run in range(args.runs):
            for arm, lanes in (("lanes", True), ("one process", False)):
                latencies = one_run(lanes, args.seconds, tmp)
                results[arm].append(latencies)
                print(
                    f"run {run + 1} {arm:11s}: {len(latencies)} commands, p50 {np.percentile(latencies, 50):.1f} ms, "
                    f"p95 {np.percentile(latencies, 95):.1f} ms, max {max(latencies):.1f} ms",
                    flush=True,
                )
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    def median_of(arm, q):
        return statistics.median(np.percentile(r, q) for r in results[arm])

    lines = [
        f"Teleop latency (ms, sent on the twin -> received on the robots' side) under {LOAD.split(':')[1]} B clouds "
        f"at {LOAD.split(':')[2]} Hz, {TELEOP_HZ} Hz commands, {args.seconds:g} s per run, median over "
        f"{args.runs} runs; loopback, no shaping; machine-bound (2 shared cores).",
        "",
        "| bridge | p50 | p95 | max |",
        "|---|---|---|---|",
    ]
    for arm in results:
        worst = statistics.median(max(r) for r in results[arm])
        lines.append(f"| {arm} | {median_of(arm, 50):.1f} | {median_of(arm, 95):.1f} | {worst:.1f} |")
    ratio = median_of("one process", 95) / max(median_of("lanes", 95), 1e-9)
    lines += ["", f"ratio one process / lanes, p95: {ratio:.2f}x"]
    print("\n" + "\n".join(lines))
    if args.write:
        with open(args.write, "w") as stream:
            stream.write("# Command lane: teleop beside clouds\n\n`python bench/command_lane_bench.py`\n\n")
            stream.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
