#!/usr/bin/env python3
"""fleet_sim with a large fleet (16 robots by default): the simulator against its anchor, same run.

Builds an N-robot fleet file in a temp folder from cps_bringup's fleet.yaml (copies of its robots
with new names at free spots in the hall's aisles, reusing their routes), then runs the real
fleet_sim node (light profile, fast renderer) on a private master, once with the code under test
and once with the anchor's cps_sim (`--anchor REV`, default main, extracted with `git archive`).
A subscriber per robot takes the clouds as the voxel filter would (rospy.AnyMsg: no decoding).

Prints per variant: received cloud Hz per robot against the configured rate, the fleet_sim
process's and its sensor workers' CPU (core-s per s, from /proc), fleet_sim's own figures from
/diagnostics (achieved rates, loop step ms, physics loop Hz, real-time factor), and our / anchor.

With --control: the robots' control beside a running fleet_sim, a velocity_mux and a
route_controller per robot (the anchor, 2N processes) against one fleet_control: processes, CPU
(core-s per s) and resident memory of the control processes.

Usage: python bench/fleet_sim_bench.py [--robots 16] [--seconds 30] [--anchor main] [--workers N]
                                       [--control] [--no-sim]
Timings on a shared machine are noisy; both variants run back to back in the same invocation.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time

import yaml
from live_fleet_sim import measure_cpu, start_fleet_sim

from cps_fleet import names
from cps_ros.processes import process_cpu_s

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FLEET_YAML = os.path.join(REPO, "catkin_ws/src/cps_bringup/config/fleet.yaml")
# Free floor in the hall's aisles (cps_sim/config/hall.yaml): west and east aisles, the central
# aisle, the north/south aisles and the corridor between tank_farm and pipe_rack.
AISLE_SPOTS = (
    (-9.0, -3.0),
    (-9.0, 0.0),
    (-9.0, 3.0),
    (0.0, -6.5),
    (0.0, -3.0),
    (0.0, 0.0),
    (0.0, 3.0),
    (0.0, 6.5),
    (9.0, -3.0),
    (9.0, 0.0),
    (9.0, 3.0),
    (-4.5, 0.0),
    (-4.5, -6.5),
    (-4.5, 6.5),
    (4.5, -6.5),
    (4.5, 6.5),
    (9.0, 6.5),
    (-9.0, 6.8),
    (-2.0, 0.0),
    (9.0, -6.5),
)


def make_fleet_file(robots, folder, source=FLEET_YAML):
    """An N-robot fleet file in `folder`: source's robots, then copies `<name>_<k>` at AISLE_SPOTS."""
    from cps_harness.fleets import fleet_doc_with_absolute_paths

    doc = fleet_doc_with_absolute_paths(source)
    originals = doc["robots"]
    if robots > len(originals) + len(AISLE_SPOTS):
        raise ValueError(f"at most {len(originals) + len(AISLE_SPOTS)} robots (free spots in the aisles)")
    out = list(originals[:robots])
    for i in range(robots - len(out)):
        template = originals[i % len(originals)]
        x, y = AISLE_SPOTS[i]
        out.append(
            {
                **template,
                "name": f"{template['name']}_{i // len(originals) + 2}",
                "initial_pose": {**template["initial_pose"], "x": x, "y": y},
            }
        )
    doc["robots"] = out
    path = os.path.join(folder, f"fleet_{robots}.yaml")
    with open(path, "w") as stream:
        yaml.safe_dump(doc, stream, sort_keys=False)
    return path


def anchor_python_path(rev, folder):
    """cps_sim's library at git revision `rev`, extracted into `folder` (put first on PYTHONPATH)."""
    target = os.path.join(folder, "anchor")
    os.makedirs(target, exist_ok=True)
    archive = subprocess.run(
        ["git", "-C", REPO, "archive", rev, "catkin_ws/src/cps_sim/src/cps_sim"], check=True, capture_output=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", target], input=archive, check=True)
    return os.path.join(target, "catkin_ws/src/cps_sim/src")


def run_variant(graph, fleet, label, seconds, workers, python_path=None, warmup_s=8.0):
    """Run fleet_sim for `seconds` after a warm-up; a dict of what was measured."""
    import rospy
    from diagnostic_msgs.msg import DiagnosticArray

    counts, lock, measuring = {}, threading.Lock(), threading.Event()
    diagnostics = {}

    def counter(name):
        def on_msg(_msg):
            if measuring.is_set():
                with lock:
                    counts[name] = counts.get(name, 0) + 1

        return on_msg

    def on_diagnostics(msg):
        if measuring.is_set():
            with lock:
                for status in msg.status:
                    if status.name.startswith("cps_sim:"):
                        diagnostics.setdefault(status.name, []).append({kv.key: kv.value for kv in status.values})

    env = dict(os.environ)
    if python_path:
        env["PYTHONPATH"] = python_path + os.pathsep + env.get("PYTHONPATH", "")
    node_graph = graph.attach()
    subs = []
    try:
        proc = start_fleet_sim(
            node_graph,
            fleet,
            f"fleet_sim_{label}",
            params={"~fleet_file": fleet.path, **({"~sensor_workers": workers} if workers is not None else {})},
            env=env,
        )
        subs = [
            rospy.Subscriber(names.robot_topic(r.name, r.cloud_topic), rospy.AnyMsg, counter(r.name), queue_size=2)
            for r in fleet.robots
        ]
        subs.append(rospy.Subscriber(names.DIAGNOSTICS, DiagnosticArray, on_diagnostics, queue_size=50))
        cpu = measure_cpu(proc, warmup_s, seconds, measuring)
    finally:
        for sub in subs:
            sub.unregister()
        node_graph.close()
    fleet_status = diagnostics.get("cps_sim: fleet", [])

    def mean_of(key):
        values = [float(d[key]) for d in fleet_status if key in d]
        return sum(values) / len(values) if values else float("nan")

    achieved = {}
    for r in fleet.robots:
        kind = "lidar" if r.has_lidar else "depth_camera"
        reports = diagnostics.get(f"cps_sim: {r.name} {kind}", [])
        achieved[r.name] = float(reports[-1]["achieved_hz"]) if reports else float("nan")
    configured = {
        r.name: (fleet.profile.lidar.rate_hz if r.has_lidar else fleet.profile.depth_camera.rate_hz)
        for r in fleet.robots
    }
    return {
        "label": label,
        "received_hz": {n: counts.get(n, 0) / seconds for n in configured},
        "configured_hz": configured,
        "achieved_hz": achieved,
        "sim_cpu": cpu[proc.pid],
        "workers_cpu": sum(v for pid, v in cpu.items() if pid != proc.pid),
        "workers": len(cpu) - 1,
        "step_ms": mean_of("step_ms_mean"),
        "step_ms_max": mean_of("step_ms_max"),
        "physics_hz": mean_of("physics_loop_hz"),
        "rtf": mean_of("real_time_factor"),
    }


def _rss_mb(pid):
    try:
        with open(f"/proc/{pid}/status") as stream:
            for line in stream:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except FileNotFoundError:
        pass
    return 0.0


def run_control_layouts(graph, fleet, seconds, warmup_s=8.0):
    """The robots' control with fleet_sim running: a velocity_mux and a route_controller per robot
    (the anchor) against one fleet_control; {layout: (processes, core-s/s, RSS MB)}."""
    sim_graph = graph.attach()
    out = {}
    try:
        start_fleet_sim(sim_graph, fleet, "fleet_sim_control", params={"~fleet_file": fleet.path})
        for layout in ("per_robot", "shared"):
            node_graph = graph.attach()
            params = {"~fleet_file": fleet.path}
            if layout == "shared":
                procs = [
                    node_graph.start_node(
                        "cps_sim",
                        "fleet_control",
                        name="fleet_control",
                        params={**params, "~robots": ",".join(fleet.robot_names)},
                    )
                ]
            else:
                procs = [
                    node_graph.start_node(
                        "cps_sim", node, name=node, namespace=names.absolute(r), params={**params, "~robot": r}
                    )
                    for r in fleet.robot_names
                    for node in ("velocity_mux", "route_controller")
                ]
            try:
                for r in fleet.robot_names:
                    node_graph.wait_for_topic(names.absolute(names.robot_topic(r, names.MISSION_STATE)), timeout_s=180)
                time.sleep(warmup_s)
                cpu0 = {p.pid: process_cpu_s(p.pid) for p in procs}
                time.sleep(seconds)
                cpu = sum(process_cpu_s(p.pid) - cpu0[p.pid] for p in procs) / seconds
                rss = sum(_rss_mb(p.pid) for p in procs)
            finally:
                node_graph.close()
            out[layout] = (len(procs), cpu, rss)
            print(f"control {layout:9s}: {len(procs):2d} processes, {cpu:.2f} core-s/s, {rss:.0f} MB resident")
    finally:
        sim_graph.close()
    (n_a, cpu_a, rss_a), (n_s, cpu_s, rss_s) = out["per_robot"], out["shared"]
    print(
        f"shared / per_robot: processes {n_s}/{n_a}, CPU {cpu_s / max(cpu_a, 1e-9):.2f}x, "
        f"memory {rss_s / max(rss_a, 1e-9):.2f}x"
    )
    return out


def report(result):
    received, configured = result["received_hz"], result["configured_hz"]
    ratios = [received[n] / configured[n] for n in configured]
    print(
        f"\n-- {result['label']}: fleet_sim {result['sim_cpu']:.2f} core-s/s, {result['workers']} sensor workers "
        f"{result['workers_cpu']:.2f} core-s/s; loop step {result['step_ms']:.1f} ms mean "
        f"(max {result['step_ms_max']:.0f}), physics loop {result['physics_hz']:.0f} Hz, real-time factor "
        f"{result['rtf']:.2f}"
    )
    print(
        f"   received Hz / configured: min {min(received.values()):.2f} Hz, min ratio {min(ratios):.2f}, "
        f"mean ratio {sum(ratios) / len(ratios):.2f}; robots below 1 Hz: "
        f"{sum(1 for v in received.values() if v < 1.0)}"
    )
    print("   " + ", ".join(f"{n} {received[n]:.1f}/{configured[n]:.0f}" for n in configured))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=30.0, help="measuring time per variant, s")
    parser.add_argument("--anchor", default="main", help="git revision of the anchor's cps_sim ('' : none)")
    parser.add_argument("--workers", type=int, default=None, help="~sensor_workers (default: the node's)")
    parser.add_argument(
        "--control",
        action="store_true",
        help="also the robots' control: fleet_control against a mux and route controller per robot",
    )
    parser.add_argument("--rounds", type=int, default=2, help="ours-then-anchor rounds")
    parser.add_argument("--no-sim", action="store_true", help="skip the simulator comparison")
    parser.add_argument("--keep", action="store_true", help="keep the temp folder (fleet file)")
    args = parser.parse_args(argv)
    os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    from cps_fleet.fleet import load_fleet
    from cps_harness.testing import RosGraph

    folder = tempfile.mkdtemp(prefix="fleet_sim_bench_")
    os.chmod(folder, 0o755)
    fleet = load_fleet(make_fleet_file(args.robots, folder), profile="light")
    print(
        f"fleet_sim with {len(fleet.robots)} robots (light profile, fast renderer) on {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f} at start, {time.strftime('%Y-%m-%d %H:%M')}; fleet file {fleet.path}"
    )
    graph = RosGraph()
    graph.start()
    os.environ.update(ROS_MASTER_URI=graph.uri, ROS_IP="127.0.0.1", ROS_HOME=graph.home)
    import rospy

    graph.point_this_process_here()
    rospy.init_node("fleet_sim_bench", anonymous=True, disable_signals=True)
    results = []
    try:
        if args.control:
            print(f"\n== The robots' control with fleet_sim running, {args.seconds:.0f} s ==")
            run_control_layouts(graph, fleet, args.seconds)
        anchor_path = anchor_python_path(args.anchor, folder) if args.anchor else None
        for round_ in range(args.rounds if not args.no_sim else 0):
            # Alternating, so that a change of the machine's load hits both variants alike.
            print(f"\n== fleet_sim, round {round_ + 1} of {args.rounds}, {args.seconds:.0f} s per variant ==")
            results.append(run_variant(graph, fleet, "ours", args.seconds, args.workers))
            report(results[-1])
            if anchor_path:
                results.append(
                    run_variant(graph, fleet, f"anchor ({args.anchor})", args.seconds, args.workers, anchor_path)
                )
                report(results[-1])
    finally:
        rospy.signal_shutdown("bench done")
        graph.close()
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)

    def min_ratio(r):
        return min(r["received_hz"][n] / r["configured_hz"][n] for n in r["configured_hz"])

    for ours, anchor in zip(results[0::2], results[1::2]):
        if not anchor["label"].startswith("anchor"):
            break
        print(
            f"\nours / anchor: min rate ratio {min_ratio(ours):.2f} / {min_ratio(anchor):.2f} = "
            f"{min_ratio(ours) / max(min_ratio(anchor), 1e-9):.2f}x; received captures/s "
            f"{sum(ours['received_hz'].values()):.0f} / {sum(anchor['received_hz'].values()):.0f}; "
            f"fleet_sim CPU {ours['sim_cpu']:.2f} / {anchor['sim_cpu']:.2f} core-s/s; loop step "
            f"{ours['step_ms']:.1f} ms; physics passes {ours['physics_hz']:.0f} / {anchor['physics_hz']:.0f} Hz"
        )
    print(f"load average at end {os.getloadavg()[0]:.1f} (other processes share these cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
