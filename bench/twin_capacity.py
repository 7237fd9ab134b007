#!/usr/bin/env python3
"""How many robots one twin core holds: a recorded mission replayed as N robots into the twin alone.

The twin's cloud path (the decoder(s) and the map server, as bringup plans them) runs in a cgroup
v1 cpuset of ONE CPU (`--twin-cpu`); the replay (cps_bringup.trace_replay: the trace's managed Draco
clouds, odometry and tf as N copies with their own names, frames and offsets in space and time, at
wall-clock rate, into the twin's decoder inputs) and this process run on the other CPUs. No
simulator, no link: this measures the twin side alone.

Per N, over a replay of `--duration` s: clouds sent (the replay's count), received, inserted and
superseded by the map server (its MapStats), and the map age p95 over every copy's 1 Hz map_age_s
from `WARMUP_S` after the replay starts to its end. A cloud is *dropped* when it was sent and
neither inserted nor superseded by a newer cloud of the same robot (lost in a transport queue, or
dropped by the map server): dropped % = 1 - (inserted + superseded) / sent. N holds when dropped
<= 1 % and map age p95 <= 1 s. N grows by doubling from `--start` until one fails, then bisects.

Layouts, in the same run: `shared` (today's default: one cloud_decoder for every robot) and the
anchor `per_robot` (one draco_decoder process per robot, the per-process layout kept to compare).
The map server's InsertCapacity at the largest N that holds gives voxel updates per second per core.

    python bench/twin_capacity.py [--bag out/trace4/mission.bag] [--duration 30] [--layouts shared,per_robot]

Without --bag it records one: a 45 s loopback mission of the default fleet, light profile. Needs
root for the cgroup (else it runs unsplit and says so). Figures into docs/benchmarks/twin_capacity.md.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import threading
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BRINGUP = os.path.join(ROOT, "catkin_ws", "src", "cps_bringup", "nodes", "cps_bringup")
REPLAY = os.path.join(ROOT, "catkin_ws", "src", "cps_bringup", "nodes", "trace_replay")
WARMUP_S = 8.0
MAX_DROPPED = 0.01
MAX_AGE_P95_S = 1.0
DRAIN_S = 3.0
# The replay keeps 20 odom -> base transforms per second per copy (recorded: ~50) and no odometry:
# the twin's cloud path needs tf at the clouds' stamps only, and one Python replay must keep up.
TF_RATE_HZ = 20.0
# A replay whose clouds leave later than this (p95) limits the trial, not the twin: marked so.
MAX_REPLAY_LATE_S = 0.1
# Robots per replay process (one Python process keeps time for ~16: 0.02 s late p95 at 16, 0.7 s at 32).
ROBOTS_PER_REPLAY = 8


class Watch:
    """The twin's MapStats and InsertCapacity, as they arrive (this process's rospy node)."""

    def __init__(self):
        import rospy

        from cps_fleet import names
        from cps_msgs.msg import InsertCapacity, MapStats

        self.lock = threading.Lock()
        self.stats, self.capacity = [], []
        rospy.Subscriber("/" + names.in_twin(names.MAP_STATS), MapStats, self._on_stats, queue_size=20)
        rospy.Subscriber("/" + names.in_twin(names.INSERT_CAPACITY), InsertCapacity, self._on_capacity, queue_size=20)

    def _on_stats(self, msg):
        with self.lock:
            self.stats.append((time.monotonic(), msg))

    def _on_capacity(self, msg):
        with self.lock:
            self.capacity.append((time.monotonic(), msg))

    def clear(self):
        with self.lock:
            self.stats, self.capacity = [], []


def record_trace(out_dir, profile, duration_s=45):
    bag = os.path.join(out_dir, "mission.bag")
    print(f"recording a {duration_s} s {profile} mission of the default fleet into {bag} ...", flush=True)
    subprocess.run(
        [sys.executable, BRINGUP, "all", "--profile", profile, "--duration", str(duration_s), "--out", out_dir]
        + ["--record", bag, "--host-cpus", "none"],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    return bag


def trial(graph, watch, split, bag, n, layout, duration_s, out_dir):
    """One replay of `n` robots; the figures of the run."""
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_bringup.supervisor import Supervisor
    from cps_bringup.trace_replay import twin_specs
    from cps_fleet.fleet import load_fleet

    folder = os.path.join(out_dir, f"{layout}_{n}")
    os.makedirs(folder, exist_ok=True)
    copies_fleet = os.path.join(folder, "copies.yaml")
    plan = subprocess.run(
        [sys.executable, REPLAY, bag, "--robots", str(n), "--duration", "1", "--copies-fleet", copies_fleet]
        + ["--plan-only"],
        capture_output=True,
        text=True,
        check=True,
    )
    robots = load_fleet(copies_fleet).robot_names
    note = next((line for line in plan.stdout.splitlines() if "asked for" in line), "")
    supervisor = Supervisor(
        twin_specs(copies_fleet, folder, layout),
        graph,
        log=lambda _m: None,
        spec_prefix=lambda spec: split.prefix(DIGITAL),
    )
    twin_pids = []
    try:
        supervisor.start_all(timeout_s=180)
        twin_pids = [supervisor.pid_of(s.label) for s in supervisor.specs]
        cpu0 = sum(_cpu_s(p) for p in twin_pids)
        watch.clear()
        start = time.monotonic()
        shards = math.ceil(n / ROBOTS_PER_REPLAY)
        replays = [
            graph.popen(
                [
                    *split.prefix(PHYSICAL),
                    sys.executable,
                    REPLAY,
                    bag,
                    "--robots",
                    str(n),
                    "--duration",
                    str(duration_s),
                ]
                + ["--copies-fleet", copies_fleet, "--no-odom", "--tf-rate", str(TF_RATE_HZ)]
                + ["--wait-for-subscribers", "30", "--shard", f"{i}/{shards}"],
                name=f"replay_{layout}_{n}_{i}",
            )
            for i in range(shards)
        ]
        for replay in replays:
            replay.wait(timeout=duration_s + 120)
        end = time.monotonic()
        time.sleep(DRAIN_S)  # the last clouds through the decoder and the slots
        cpu_s = sum(_cpu_s(p) for p in twin_pids) - cpu0
    finally:
        supervisor.stop_all()
    sent, late, stalls = {}, [], []
    for i in range(shards):
        output = graph.output(f"replay_{layout}_{n}_{i}")
        sent_line = next((line for line in reversed(output.splitlines()) if "sent clouds:" in line), None)
        if sent_line is None:
            raise RuntimeError(f"the replay of {n} (shard {i}) did not finish: {output[-2000:]}")
        summary = json.loads(sent_line[sent_line.index("{") :])
        sent.update(summary["sent"])
        late.append(summary["late_p95_s"])
        stalls += summary.get("stalls_s", [])
    summary = dict(late_p95_s=max(late), stalls_s=stalls)
    with watch.lock:
        stats, capacity = list(watch.stats), list(watch.capacity)
    if not stats:
        raise RuntimeError("no map_stats from the map server")
    last = {r.robot: r for r in stats[-1][1].robots}
    # The window starts WARMUP_S after the first copy's first insertion (the replay reads its trace first).
    first = next((t for t, msg in stats if any(r.clouds_inserted for r in msg.robots if r.robot in robots)), end)
    start = first
    ages = [r.map_age_s for t, msg in stats if first + WARMUP_S <= t <= end for r in msg.robots if r.robot in robots]
    inserted = sum(last[r].clouds_inserted for r in robots if r in last)
    received = sum(last[r].clouds_received for r in robots if r in last)
    lost_at_server = sum(
        last[r].clouds_dropped_queue + last[r].clouds_dropped_tf + last[r].clouds_dropped_invalid
        for r in robots
        if r in last
    )
    waiting = sum(last[r].queue_length for r in robots if r in last)
    superseded = max(0, received - inserted - lost_at_server - waiting)
    total_sent = sum(sent.values())
    dropped = total_sent - inserted - superseded - waiting
    steady = [m for t, m in capacity if t >= start + WARMUP_S]
    cap = steady[-1] if steady else (capacity[-1][1] if capacity else None)
    age_p95 = float(np.percentile(ages, 95)) if ages else math.inf
    row = dict(
        layout=layout,
        asked=n,
        robots=len(robots),
        note=note,
        sent=total_sent,
        received=received,
        inserted=inserted,
        superseded=superseded,
        dropped=dropped,
        dropped_pct=100.0 * dropped / total_sent if total_sent else 100.0,
        superseded_pct=100.0 * superseded / total_sent if total_sent else 0.0,
        age_p95_s=age_p95,
        twin_cpu_s_per_s=cpu_s / max(end - start + DRAIN_S, 1e-9),
        busy_s=cap.busy_s if cap else 0.0,
        window_s=cap.window_s if cap else 0.0,
        clouds_per_s_capacity=cap.clouds_per_s if cap else 0.0,
        voxel_updates_per_s_capacity=cap.voxel_updates_per_s if cap else 0.0,
        insertion_voxel_updates_per_busy_s=(cap.voxel_updates_per_s / 0.8) if cap else 0.0,
    )
    row["replay_late_p95_s"] = summary["late_p95_s"]
    row["replay_stalls_s"] = summary["stalls_s"]
    row["replay_limited"] = summary["late_p95_s"] > MAX_REPLAY_LATE_S or bool(summary["stalls_s"])
    row["holds"] = row["dropped_pct"] <= 100 * MAX_DROPPED and row["age_p95_s"] <= MAX_AGE_P95_S
    return row


def _cpu_s(pid):
    """User + system CPU seconds of a process and its waited-for children (0 once it has ended)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return sum(int(x) for x in fields[11:15]) / os.sysconf("SC_CLK_TCK")
    except OSError:
        return 0.0


def search(run, start_n, max_n):
    """Doubling from start_n until one fails (or max_n), then bisect; every row run. A trial whose
    replay stalled or ran late is run once more; limited again, the search stops there: the machine,
    not the twin, was the limit (said in the report)."""
    rows, good, bad = [], 0, None

    def judged(n):
        row = run(n)
        rows.append(row)
        print(_line(row), flush=True)
        if not row["holds"] and row["replay_limited"]:
            row = run(n)
            rows.append(row)
            print(_line(row), flush=True)
        return row

    n = start_n
    while n <= max_n:
        row = judged(n)
        if not row["holds"] and row["replay_limited"]:
            return good, rows
        if row["robots"] < n:  # the trace could not place more: no larger N to try
            good = row["robots"] if row["holds"] else good
            bad = None if row["holds"] else row["robots"]
            break
        if row["holds"]:
            good = n
            n *= 2
        else:
            bad = n
            break
    while bad is not None and bad - good > max(1, good // 4):
        n = (good + bad) // 2
        row = judged(n)
        if not row["holds"] and row["replay_limited"]:
            return good, rows
        good, bad = (n, bad) if row["holds"] else (good, n)
    return good, rows


def _line(r):
    return (
        f"  {r['layout']:9s} N={r['robots']:3d}: sent {r['sent']:5d}, inserted {r['inserted']:5d}, superseded "
        f"{r['superseded_pct']:5.1f} %, dropped {r['dropped_pct']:5.2f} %, map age p95 {r['age_p95_s']:.2f} s, twin "
        f"CPU {r['twin_cpu_s_per_s']:.2f} cores, capacity {r['clouds_per_s_capacity']:.0f} clouds/s "
        f"{r['voxel_updates_per_s_capacity'] / 1e6:.2f} M voxel updates/s, replay late p95 {r['replay_late_p95_s']:.3f} s"
        f" -> {'holds' if r['holds'] else 'fails'}{' (replay-limited)' if r['replay_limited'] else ''}"
    )


def report(results, split_text, args, bag):
    lines = [
        "# Twin capacity: robots per twin core (issue 26)",
        "",
        "Generated by `bench/twin_capacity.py`. A recorded mission's managed clouds, odometry and tf are "
        "replayed as N robots (cps_bringup.trace_replay) into the twin's decoder(s) and map server, which run "
        f"on one CPU. {split_text}. Trace: `{bag}` ({args.profile} profile, 4 robots); each trial replays "
        f"{args.duration:.0f} s at wall-clock rate.",
        "",
        f"A N holds when dropped <= {100 * MAX_DROPPED:g} % (sent and neither inserted nor superseded by a newer "
        f"cloud of the same robot) and map age p95 <= {MAX_AGE_P95_S:g} s (every copy's map_age_s at 1 Hz from "
        f"{WARMUP_S:g} s after the replay starts to its end). Superseded clouds (the map server's slot of one per "
        "robot keeps the newest) are shown apart: not lost, but not inserted either.",
        "",
        "**Contended machine:** two cores shared with other sessions' builds and tests while this ran; the twin's "
        "CPU was not idle-exclusive. Treat the figures as a lower bound of one free core.",
        "",
        "| layout | largest N held on the (shared) twin CPU | twin CPU at that N (cores) | robots per free core "
        "(N / twin CPU) | voxel updates/s per core of insertion | ratio to the anchor (robots per free core) |",
        "|---|---|---|---|---|---|",
    ]
    per_free_core = {}
    for layout, (good, rows) in results.items():
        best = next((r for r in rows if r["robots"] == good and r["holds"]), None)
        per_free_core[layout] = best["robots"] / best["twin_cpu_s_per_s"] if best and best["twin_cpu_s_per_s"] else None
    anchor = per_free_core.get("per_robot")
    for layout, (good, rows) in results.items():
        best = next((r for r in rows if r["robots"] == good and r["holds"]), None)
        per_core = f"{best['insertion_voxel_updates_per_busy_s'] / 1e6:.2f} M" if best else "-"
        free = per_free_core[layout]
        ratio = f"{free / anchor:.2f}x" if free and anchor else "-"
        cpu = f"{best['twin_cpu_s_per_s']:.2f}" if best else "-"
        limited = bool(rows) and rows[-1]["replay_limited"] and not rows[-1]["holds"]
        held = f">= {good} (beyond: the replay stalled, machine-limited)" if limited else str(good)
        lines.append(f"| {layout} | {held} | {cpu} | {f'{free:.0f}' if free else '-'} | {per_core} | {ratio} |")
    lines += [
        "",
        "Voxel updates per second per core = the map server's InsertCapacity voxel_updates_per_s at the largest "
        "N held, divided by its insertion budget (0.8): ray-caster voxel steps per second of insertion time on "
        "that core (the unit voxblox and OctoMap quote).",
        "",
        "Insertion busy = the map server's insertion wall time per second (InsertCapacity busy_s / window_s, "
        "the last window of the trial); the twin's CPU (decoder(s) and map server, from /proc) less the "
        "insertion is decoding, deserialising and publishing. Wall time counts preemption too.",
        "",
        "## Every trial",
        "",
        "| layout | N | sent | inserted | superseded % | dropped % | map age p95 s | twin CPU (cores) | "
        "insertion busy (s per s) | capacity clouds/s | capacity M voxel updates/s | replay late p95 s | holds |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for layout, (_, rows) in results.items():
        for r in rows:
            lines.append(
                f"| {layout} | {r['robots']}{' (asked ' + str(r['asked']) + ')' if r['robots'] != r['asked'] else ''} "
                f"| {r['sent']} | {r['inserted']} | {r['superseded_pct']:.1f} | {r['dropped_pct']:.2f} | "
                f"{r['age_p95_s']:.2f} | {r['twin_cpu_s_per_s']:.2f} | "
                f"{r['busy_s'] / r['window_s'] if r['window_s'] else 0:.2f} | {r['clouds_per_s_capacity']:.0f} | "
                f"{r['voxel_updates_per_s_capacity'] / 1e6:.2f} | {r['replay_late_p95_s']:.3f} | "
                f"{'yes' if r['holds'] else 'no'}{' (replay-limited)' if r['replay_limited'] else ''} |"
            )
    notes = sorted({r["note"] for _, rows in results.values() for r in rows if r["note"]})
    if notes:
        lines += ["", *[f"- {n}" for n in notes]]
    return "\n".join(lines) + "\n"


def _stop_on_sigterm():
    import signal

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")  # the cgroups and the master are cleaned up

    signal.signal(signal.SIGTERM, handler)


def main():
    _stop_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bag", default=None, help="a mission bag (default: record one)")
    parser.add_argument("--profile", default="light", help="the profile the trace was (or is) recorded with")
    parser.add_argument("--duration", type=float, default=30.0, metavar="S")
    parser.add_argument("--layouts", default="shared,per_robot")
    parser.add_argument("--start", type=int, default=4)
    parser.add_argument("--max", type=int, default=128)
    parser.add_argument(
        "--twin-shares",
        type=int,
        default=16384,
        help="the twin group's cpu.shares: on a machine shared with other work, the twin gets its CPU first "
        "(a plain process weighs 1024), the closest this machine comes to a free core",
    )
    parser.add_argument("--replay-shares", type=int, default=16384, help="the replay's cpu.shares (it must keep time)")
    parser.add_argument("--twin-cpu", type=int, default=None, help="the twin's CPU (default: the last)")
    parser.add_argument("--out", default=os.path.join(ROOT, "bench", "out", "twin_capacity"))
    parser.add_argument("--split-text", default="", help=argparse.SUPPRESS)
    parser.add_argument("--from-json", default=None, help="only write the report from an earlier results.json")
    parser.add_argument("--md", default=os.path.join(ROOT, "docs", "benchmarks", "twin_capacity.md"))
    args = parser.parse_args()

    if args.from_json:
        with open(args.from_json) as f:
            saved = json.load(f)
        if "results" not in saved:  # the first format: {layout: rows}
            held = {k: [r["robots"] for r in rows if r["holds"]] for k, rows in saved.items()}
            saved = dict(
                results={k: dict(good=max(held[k], default=0), rows=rows) for k, rows in saved.items()},
                split=args.split_text,
                bag=args.bag,
            )
        results = {k: (v["good"], v["rows"]) for k, v in saved["results"].items()}
        with open(args.md, "w") as f:
            f.write(report(results, saved["split"], args, saved["bag"]))
        return

    from cps_bringup.host_split import HostSplit, online_cpus
    from cps_bringup.plan import DIGITAL, PHYSICAL
    from cps_ros.processes import RosGraph, free_port

    os.makedirs(os.path.join(args.out, "logs"), exist_ok=True)
    bag = args.bag or record_trace(os.path.join(args.out, "trace"), args.profile)
    if not bag.endswith(".trace.bag"):
        from cps_bringup.trace_replay import compact_trace
        from cps_fleet.fleet import load_fleet

        compact = os.path.join(args.out, os.path.basename(bag).replace(".bag", "") + ".trace.bag")
        if not os.path.exists(compact):
            compact_trace(bag, load_fleet(), compact, busy_only=True)
        bag = compact
    cpus = online_cpus()
    twin = args.twin_cpu if args.twin_cpu is not None else cpus[-1]
    robots_side = tuple(c for c in cpus if c != twin) or cpus
    split = HostSplit.choose(
        {PHYSICAL: robots_side, DIGITAL: (twin,)},
        name=f"cps_twin_capacity_{os.getpid()}",
        shares={DIGITAL: args.twin_shares, PHYSICAL: args.replay_shares},
    )
    split_text = split.describe()
    print(split_text, flush=True)
    results = {}
    with split, RosGraph(port=free_port(), log_dir=os.path.join(args.out, "logs")) as graph:
        import rospy

        graph.point_this_process_here()
        rospy.init_node("twin_capacity_bench", anonymous=True, disable_signals=True)
        watch = Watch()
        for layout in args.layouts.split(","):
            print(f"{layout}:", flush=True)
            results[layout] = search(
                lambda n, layout=layout: trial(graph, watch, split, bag, n, layout, args.duration, args.out),
                args.start,
                args.max,
            )
        rospy.signal_shutdown("done")
    text = report(results, split_text, args, os.path.relpath(bag, ROOT))
    with open(os.path.join(args.out, "results.json"), "w") as f:
        saved = {k: dict(good=v[0], rows=v[1]) for k, v in results.items()}
        json.dump(dict(results=saved, split=split_text, bag=os.path.relpath(bag, ROOT)), f, indent=1)
    with open(args.md, "w") as f:
        f.write(text)
    print(text)


if __name__ == "__main__":
    main()
