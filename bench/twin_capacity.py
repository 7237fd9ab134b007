#!/usr/bin/env python3
"""How the twin bends under more robots than it can serve (issue 37): a recorded mission replayed as
N = 8 ... 128 robots into the twin alone, on one and on two twin CPUs, light and paper profiles.

The twin's cloud path is the map server (its receive process takes the managed Draco clouds as the
link delivers them; the insertion decodes only what it inserts) in a cgroup v1 cpuset of
`--twin-cpus` CPUs; the replay (cps_bringup.trace_replay: the trace's managed clouds and tf as N
copies with their own names, frames and offsets in space and time, at wall-clock rate, published
synchronously so that nothing is dropped unseen before the twin) runs on the other CPU (with two
twin CPUs on a two-core machine: on the same two, at the same cpu.shares). Per N, from the nodes'
own counters (cps_experiments.twin_replay): clouds sent, inserted, superseded and dropped by cause
(they sum to sent), inserted clouds and points per second, map age p95 (every robot pooled; per
robot, the oldest against the median), twin CPU and the insertion's CPU.

The anchor, measured in the same run on the same clouds (the trace's, decoded and placed with its
tf) on the twin's CPU: plain sequential OctoMap insertion (octomap-python's insertPointCloud per
cloud, what octomap_server does), and the map server's own per-cloud path run alone (decode,
prepare, insert), both in CPU time of one thread.

    python bench/twin_capacity.py sweep --profile light --twin-cpus 1 [--robots 8,16,...] [--duration 30]
    python bench/twin_capacity.py report    # docs/benchmarks/twin_capacity.md and its plot

A sweep records its trace first when there is none (a loopback mission of the default fleet; the
paper profile's simulator reaches ~6 % of its camera rate on two cores, so its trace is replayed at
the profile's sensor rates: each robot's trace stretched in time, trace_replay --profile-rates).
Needs root for the cgroups (else it runs unsplit and says so). Run it under the heavy lock.
"""

import argparse
import datetime
import json
import os
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "bench", "out", "twin_capacity")
# The sweeps, committed: {"sweeps": {"<profile>/<twin CPUs>": sweep}} (the report and the README read it).
RESULTS = os.path.join(ROOT, "docs", "benchmarks", "twin_capacity_results.json")
MD = os.path.join(ROOT, "docs", "benchmarks", "twin_capacity.md")
PLOT = os.path.join(ROOT, "docs", "benchmarks", "figures", "twin_capacity.png")
ROBOTS = (8, 12, 16, 24, 32, 48, 64, 96, 128)
RECORD_S = {"light": 60, "paper": 90}
MIN_BUSY_HZ = {"light": 3, "paper": 1}
ANCHOR_CLOUDS = 240


def record_trace(profile):
    """The compacted trace of a loopback mission of the default fleet in `profile` (recorded once)."""
    from cps_bringup.trace_replay import compact_trace
    from cps_fleet.fleet import load_fleet
    from cps_harness.mission import run_mission

    folder = os.path.join(OUT, f"trace_{profile}")
    bag, trace = os.path.join(folder, "mission.bag"), os.path.join(folder, "mission.trace.bag")
    if os.path.exists(trace):
        return trace
    if not os.path.exists(bag):
        os.makedirs(folder, exist_ok=True)
        print(f"recording a {RECORD_S[profile]} s {profile} mission of the default fleet into {bag} ...", flush=True)
        run_mission(
            folder,
            ["--profile", profile, "--duration", str(RECORD_S[profile]), "--record", bag, "--host-cpus", "none"],
            timeout_s=RECORD_S[profile] + 600,
        )
    return compact_trace(bag, load_fleet(), trace, busy_only=True, min_busy_hz=MIN_BUSY_HZ[profile])


def placed_clouds(trace_path, profile, limit):
    """[(robot, decoded PointCloud2 message, points in map, origin, max range)] of the trace's first
    clouds, round-robin over its robots, placed with the trace's own tf."""
    import genpy
    import tf2_py

    from cps_bringup.trace_replay import load_trace
    from cps_fleet import names
    from cps_fleet.fleet import load_fleet
    from cps_mapping.cloud_input import prepare_cloud, quaternion_matrix, read_leaf
    from cps_transport.draco import DracoDecoder
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    fleet = load_fleet(profile=profile)
    trace = load_trace(trace_path, fleet)
    buffer = tf2_py.BufferCore(genpy.Duration(3600))
    for robot in trace.robots.values():
        for t in robot.tf_static:
            buffer.set_transform_static(t, "bench")
        for _, t in robot.tf:
            buffer.set_transform(t, "bench")
    decoder, out = DracoDecoder(), []
    streams = {name: list(robot.clouds) for name, robot in trace.robots.items()}
    while len(out) < limit and any(streams.values()):
        for name, stream in streams.items():
            if not stream or len(out) >= limit:
                continue
            _, compressed = stream.pop(0)
            try:
                tf = buffer.lookup_transform_core(names.MAP_FRAME, compressed.header.frame_id, compressed.header.stamp)
            except tf2_py.TransformException:
                continue
            cloud = decoder.decode(compressed)
            points = cloud_to_array(cloud)
            q, t = tf.transform.rotation, tf.transform.translation
            leaf, _ = read_leaf(points)
            prepared = prepare_cloud(
                xyz_of(points), quaternion_matrix(q.x, q.y, q.z, q.w), (t.x, t.y, t.z), 200.0, leaf, 0.1
            )
            max_range = fleet.mapping.max_range_m[fleet.robot(name).type]
            out.append((name, compressed, prepared.points_m, prepared.origin_m, max_range, (q, t)))
    return fleet, out


def anchor(trace_path, profile, twin_cpus):
    """Plain sequential OctoMap insertion and the map server's own per-cloud path, on the same
    clouds, one thread pinned to the twin's CPUs: clouds and points per CPU-second."""
    from cps_mapping.cloud_input import prepare_cloud, quaternion_matrix, read_leaf
    from cps_mapping.fused_map import FusedLogOddsMap, new_octree
    from cps_mapping.log_odds_grid import warm_up
    from cps_transport.draco import DracoDecoder
    from cps_transport.pointcloud import cloud_to_array, xyz_of

    fleet, clouds = placed_clouds(trace_path, profile, ANCHOR_CLOUDS)
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, set(twin_cpus))
    try:
        warm_up()
        tree = new_octree(fleet.mapping.resolution_m, fleet.mapping.sensor_model)
        start = time.thread_time()
        for _, _, points, origin, max_range, _ in clouds:
            tree.insertPointCloud(points, origin, maxrange=max_range)
        plain_s = time.thread_time() - start
        fused, decoder = FusedLogOddsMap.from_mapping_config(fleet.mapping), DracoDecoder()
        start = time.thread_time()
        for robot, compressed, _, _, max_range, (q, t) in clouds:
            points = cloud_to_array(decoder.decode(compressed))
            leaf, _ = read_leaf(points)
            prepared = prepare_cloud(
                xyz_of(points), quaternion_matrix(q.x, q.y, q.z, q.w), (t.x, t.y, t.z), 200.0, leaf, 0.1
            )
            fused.insert_cloud(prepared.points_m, prepared.origin_m, max_range_m=max_range, robot=robot)
        ours_s = time.thread_time() - start
    finally:
        os.sched_setaffinity(0, before)
    points = sum(len(c[2]) for c in clouds)
    return dict(
        clouds=len(clouds),
        points=points,
        plain_clouds_per_cpu_s=len(clouds) / plain_s,
        plain_points_per_cpu_s=points / plain_s,
        ours_clouds_per_cpu_s=len(clouds) / ours_s,
        ours_points_per_cpu_s=points / ours_s,
    )


def sweep(args):
    from cps_experiments.twin_replay import replay_bench, replay_tf_rate_hz

    trace = args.bag or record_trace(args.profile)
    cpus = tuple(range(os.cpu_count()))[-args.twin_cpus :]
    print(f"anchor on CPU {cpus} ...", flush=True)
    figures = anchor(trace, args.profile, cpus)
    print(json.dumps(figures), flush=True)
    replay_args = ("--profile-rates", args.profile) if args.profile != "light" else ()
    tf_rate_hz = replay_tf_rate_hz(args.profile)
    nice = () if args.receive_nice is None else (f"_receive_nice:={args.receive_nice}",)
    label = f"{args.profile}_{args.twin_cpus}cpu" + ("" if args.receive_nice is None else f"_nice{args.receive_nice}")
    rows = []
    started = datetime.datetime.now().isoformat(timespec="minutes")
    load_before = os.getloadavg()
    with replay_bench(OUT, twin_cpus=cpus, name="cps_twin_capacity") as (run, split_text):
        print(split_text, flush=True)
        for n in [int(x) for x in args.robots.split(",")]:
            row = run(n, trace, args.duration, label, replay_args, nice, tf_rate_hz)
            if row["replay_limited"]:  # the machine, not the twin: once more
                print(f"  N={n}: replay late (p95 {row['replay_late_p95_s']:.3f} s), once more", flush=True)
                row = run(n, trace, args.duration, label, replay_args, nice, tf_rate_hz)
            rows.append(row)
            print(_line(row), flush=True)
    key = f"{args.profile}/{args.twin_cpus}" + ("" if args.receive_nice is None else f"/nice{args.receive_nice}")
    saved = _load()
    saved[key] = dict(
        profile=args.profile,
        twin_cpus=args.twin_cpus,
        receive_nice=args.receive_nice,  # None: the map server's default
        split=split_text,
        trace=os.path.relpath(trace, ROOT),
        duration_s=args.duration,
        tf_rate_hz=tf_rate_hz,
        started=started,
        load_before=load_before,
        load_after=os.getloadavg(),
        anchor=figures,
        rows=rows,
    )
    with open(RESULTS, "w") as f:
        json.dump({"sweeps": saved}, f, indent=1, default=float)
    print(f"saved {key} into {RESULTS}")


def _load():
    """{key: sweep} saved so far; {} for none, or for issue 26's file (its layouts: in git history)."""
    if not os.path.exists(RESULTS):
        return {}
    with open(RESULTS) as f:
        return json.load(f).get("sweeps", {})


def _line(r):
    return (
        f"  N={r['robots']:3d}: offered {r['offered_clouds_per_s']:6.1f}/s inserted {r['inserted_clouds_per_s']:6.1f}/s "
        f"({r['inserted_points_per_s'] / 1e3:5.0f} k pts/s), superseded {r['superseded_pct']:5.1f} %, dropped "
        f"{r['dropped_pct']:5.2f} %, unaccounted {r['clouds_unaccounted']}, age p95 {r['age_p95_s']:.2f} s (oldest "
        f"robot {r['oldest_robot_age_p95_s']:.2f}, median {r['median_robot_age_p95_s']:.2f}, bar {r['age_bar_s']:.2f}), "
        f"twin CPU {r['twin_cpu_s_per_s']:.2f} (receive {r['receive_cpu_s_per_s']:.2f}, insertion "
        f"{r['insertion_cpu_s_per_s']:.2f}), replay late {r['replay_late_p95_s']:.3f} s"
    )


def _table(rows):
    head = (
        "| N | offered clouds/s | inserted clouds/s | points/s | superseded | queue | decoder | tf | map server | "
        "waiting | unaccounted | sent | map age p50 / p95 s | oldest / median robot p95 s | bar 1.5 N/R s | "
        "twin CPU (receive, insertion) | replay late p95 s |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in sorted(rows, key=lambda r: r["robots"]):
        lines.append(
            f"| {r['robots']} | {r['offered_clouds_per_s']:.0f} | {r['inserted_clouds_per_s']:.1f} | "
            f"{r['inserted_points_per_s'] / 1e3:.0f} k | {r['clouds_superseded']} | {r['clouds_queue']} | "
            f"{r['clouds_decoder']} | {r['clouds_tf']} | {r['clouds_map_server']} | {r['clouds_waiting']} | "
            f"{r['clouds_unaccounted']} | {r['sent']} | {r['age_p50_s']:.2f} / {r['age_p95_s']:.2f} | "
            f"{r['oldest_robot_age_p95_s']:.2f} / {r['median_robot_age_p95_s']:.2f} | {r['age_bar_s']:.2f} | "
            f"{r['twin_cpu_s_per_s']:.2f} ({r['receive_cpu_s_per_s']:.2f}, {r['insertion_cpu_s_per_s']:.2f}) | "
            f"{r['replay_late_p95_s']:.3f}{' (limited)' if r['replay_limited'] else ''} |"
        )
    return lines


def plot(saved, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_rate, ax_age) = plt.subplots(1, 2, figsize=(12, 4.5))
    for _key, sweep_ in sorted(saved.items()):
        rows = sorted(sweep_["rows"], key=lambda r: r["robots"])
        n = [r["robots"] for r in rows]
        name = f"{sweep_['profile']}, {sweep_['twin_cpus']} twin CPU" + (
            f", receive nice {sweep_['receive_nice']}" if sweep_.get("receive_nice") is not None else ""
        )
        line = ax_rate.plot(n, [r["inserted_clouds_per_s"] for r in rows], "o-", label=f"{name}: inserted")[0]
        ax_rate.plot(n, [r["offered_clouds_per_s"] for r in rows], ":", color=line.get_color(), alpha=0.6)
        ax_age.plot(n, [r["age_p95_s"] for r in rows], "o-", color=line.get_color(), label=f"{name}: p95")
        ax_age.plot(n, [r["age_bar_s"] for r in rows], "--", color=line.get_color(), alpha=0.5)
    ax_rate.set(xscale="log", xlabel="replayed robots N", ylabel="clouds/s", title="inserted (offered dotted)")
    ax_age.set(xscale="log", yscale="log", xlabel="replayed robots N", ylabel="map age p95 s")
    ax_age.set_title("map age p95 (dashed: the bar 1.5 N / inserted per s)")
    ax_age.axhline(1.0, color="grey", lw=0.8)
    for ax in (ax_rate, ax_age):
        ax.set_xticks(ROBOTS)
        ax.set_xticklabels([str(n) for n in ROBOTS])
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fig.savefig(path, dpi=110)


def report(_args):
    from cps_experiments.twin_replay import (
        MAX_AGE_P95_S,
        MAX_DROPPED,
        MAX_FALL,
        MAX_OLDEST_OVER_MEDIAN,
        MAX_SUPERSEDED,
        judge_sweep,
    )

    saved = _load()
    plot(saved, PLOT)
    lines = [
        "# Twin capacity: a twin that bends and never breaks (issue 37)",
        "",
        f"Generated by `bench/twin_capacity.py report` from `{os.path.relpath(RESULTS, ROOT)}` (the sweeps below, "
        "each one run under the heavy lock). A recorded mission's managed clouds and tf are replayed as N robots "
        "(cps_bringup.trace_replay) into the twin alone: the map server, whose receive process holds each robot's "
        "latest cloud as it arrived and whose insertion decodes and inserts only what it takes, the robot whose map "
        "is oldest first. Every cloud is accounted for by the nodes' own counters: sent (the replay's publish() "
        "returned) = inserted + superseded + dropped by cause + still waiting + unaccounted.",
        "",
        f"![twin capacity]({os.path.relpath(PLOT, os.path.dirname(MD))})",
        "",
    ]
    for key, s in sorted(saved.items()):
        verdict = judge_sweep(s["rows"])
        above = sorted(r["robots"] for r in s["rows"] if r["robots"] > verdict["capacity"])
        a = s["anchor"]
        sat = max(s["rows"], key=lambda r: r["inserted_clouds_per_s"])
        lines += [
            f"## {s['profile']} profile, {s['twin_cpus']} twin CPU{'s' if s['twin_cpus'] > 1 else ''}"
            + (f", the receive process at nice {s['receive_nice']}" if s.get("receive_nice") is not None else ""),
            "",
            f"{s['split']}. Trace `{s['trace']}`; each N replays {s['duration_s']:g} s"
            + (
                f" with {s['tf_rate_hz']:g} transforms per second per robot (twin_replay.replay_tf_rate_hz)"
                if "tf_rate_hz" in s
                else " with 20 transforms per second per robot (then the replay's one rate)"
            )
            + f"; run {s['started']}, machine "
            f"load (1/5/15 min) {', '.join(f'{x:.1f}' for x in s['load_before'])} before and "
            f"{', '.join(f'{x:.1f}' for x in s['load_after'])} after (a shared 2-core machine: figures are "
            "machine-bound).",
            "",
            *_table(s["rows"]),
            "",
            f"- **Capacity, measured:** {verdict['capacity']} robots on {s['twin_cpus']} twin CPU"
            f"{'s' if s['twin_cpus'] > 1 else ''} ({verdict['capacity'] / s['twin_cpus']:g} per twin core): the "
            f"largest N run that holds (<= {100 * MAX_DROPPED:g} % of the clouds sent lost, <= "
            f"{100 * MAX_SUPERSEDED:g} % superseded, every robot's map age p95 <= {MAX_AGE_P95_S:g} s); "
            + (
                f"the next N run, {above[0]}, does not: the capacity lies between."
                if above and verdict["capacity"]
                else (f"no N run holds, not even {above[0]}." if above else "no larger N was run.")
            ),
            f"- **Freshness alone** (issue 37's words: every robot's map age p95 <= {MAX_AGE_P95_S:g} s, <= "
            f"{100 * MAX_DROPPED:g} % lost; superseded not judged): {verdict['fresh_capacity']} robots.",
            f"- **No cliff** (inserted clouds/s never more than {MAX_FALL:.0%} below its highest at a smaller N, "
            f"from the capacity to N = {max(r['robots'] for r in s['rows'])}): worst fall {verdict['worst_fall']:.1%}, "
            f"{'holds' if verdict['no_cliff'] else 'FAILS'}.",
            f"- **Freshness beyond capacity** (map age p95 <= 1.5 N / inserted per s): "
            f"{'holds' if verdict['fresh_beyond'] else 'FAILS'}; **no robot starves** (oldest robot's p95 within "
            f"{MAX_OLDEST_OVER_MEDIAN:g}x the median robot's): {'holds' if verdict['no_starving'] else 'FAILS'}.",
            f"- **Drops by cause sum to sent:** {'every N' if verdict['ledger'] else 'NOT for every N'}.",
            f"- **Anchor, same run, same {a['clouds']} clouds ({a['points'] / a['clouds']:.0f} points each on "
            f"average), one thread on the twin's CPU:** plain sequential OctoMap insertion "
            f"{a['plain_clouds_per_cpu_s']:.1f} clouds (= {a['plain_points_per_cpu_s'] / 1e3:.0f} k points) per "
            f"CPU-second; the map server's own per-cloud path alone (Draco decode, prepare, insert) "
            f"{a['ours_clouds_per_cpu_s']:.1f} clouds per CPU-second ({a['ours_clouds_per_cpu_s'] / a['plain_clouds_per_cpu_s']:.1f}x). "
            f"The live twin inserted at most {sat['inserted_clouds_per_s']:.1f} clouds/s (N = {sat['robots']}) on "
            f"{s['twin_cpus']} CPU{'s' if s['twin_cpus'] > 1 else ''}: "
            f"{sat['inserted_clouds_per_s'] / s['twin_cpus'] / a['plain_clouds_per_cpu_s']:.1f}x plain OctoMap's "
            "rate per core (receiving, tf and publishing included; the replay runs on the other CPU).",
            "",
        ]
    lines += [
        "What these figures say and do not say, written by hand, and the run before issue 37 (the twin's decoder "
        "processes, two layouts) with its reading: [twin_capacity_reading.md](twin_capacity_reading.md).",
    ]
    with open(MD, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"wrote {MD} and {PLOT}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("sweep", help="one profile on one number of twin CPUs; results into results.json")
    run.add_argument("--profile", choices=("light", "paper"), default="light")
    run.add_argument("--twin-cpus", type=int, choices=(1, 2), default=1)
    run.add_argument("--robots", default=",".join(map(str, ROBOTS)))
    run.add_argument("--duration", type=float, default=30.0, metavar="S")
    run.add_argument(
        "--receive-nice", type=int, default=None, help="the map server's ~receive_nice (default: its own default)"
    )
    run.add_argument("--bag", default=None, help="a compacted trace (default: record one for the profile)")
    sub.add_parser("report", help="docs/benchmarks/twin_capacity.md and the plot from results.json")
    args = parser.parse_args()
    {"sweep": sweep, "report": report}[args.command](args)


if __name__ == "__main__":
    import signal

    def _stop(signum, _frame):
        raise KeyboardInterrupt(f"signal {signum}")  # the cgroups and the master are cleaned up

    signal.signal(signal.SIGTERM, _stop)
    main()
