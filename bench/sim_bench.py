#!/usr/bin/env python3
"""cps_sim benchmark: the fast renderer (moderngl + Embree) against PyBullet's, in the same run.

1. Sensor costs, each renderer in its own child process (PyBullet's EGL plugin and a moderngl
   context cannot share one): ms per 640x480 and 160x120 colour+depth frame (render, depth
   linearisation and the organized cloud; render() alone is the colour+depth frame the renderer
   gives) and per lidar scan (16 x 1875 rays). PyBullet's figure
   is its cheaper renderer for the size (EGL at 640x480, TinyRenderer at 160x120), as 'auto' picks.
2. Core-seconds per mission-second of the light-profile fleet: the sensor worker pool (2
   processes) driven by the fleet_sim's earliest-deadline-first scheduler at the configured rates
   for --seconds, CPU time of this process and the workers read from /proc.
3. The paper profile (640x480 @ 30 Hz depth x 3, 16x1875 @ 10 Hz lidar), sensors alone with the
   fast renderer: achieved rate per sensor against the configured one.
4. Optional (--node): the real fleet_sim node on a private master, per renderer (rates received).

Usage: python bench/sim_bench.py [--frames 15] [--seconds 20] [--workers 2] [--node]
Timings on a shared machine are noisy; figures are medians and ratios from the same run.
"""

import argparse
import math
import multiprocessing
import os
import statistics
import sys
import time

from cps_fleet import names
from cps_ros.processes import process_cpu_s

FRAME_SIZES = ((640, 480), (160, 120))
PYBULLET_FOR_SIZE = {640: "egl", 160: "tiny"}


def _median_ms(fn, repeats):
    fn()  # warm-up (first frame compiles shaders)
    wall = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        wall.append(1000.0 * (time.perf_counter() - start))
    return statistics.median(wall)


def _sensor_costs(renderer, frames):
    """{what: median ms} for one renderer; runs in a child process."""
    from cps_fleet.fleet import load_fleet
    from cps_sim.sample_clouds import SAMPLE_POSES
    from cps_sim.sensors import DepthCamera
    from cps_sim.simulation import FleetSimulation

    fleet = load_fleet(profile="paper")
    cam_cfg = fleet.profile.depth_camera
    sim = FleetSimulation(fleet, renderer=renderer)
    try:
        for name, (x, y, z, yaw_deg) in SAMPLE_POSES.items():
            sim.place(name, x, y, z, math.radians(yaw_deg))
        optical = sim.robots["jackal"].robot.sensor_in_map()
        out = {"renderer": sim.renderer}
        for width, height in FRAME_SIZES:
            camera = DepthCamera(sim.world, width, height, cam_cfg.hfov_deg, cam_cfg.near_m, cam_cfg.far_m)
            view = camera.view_matrix(optical)
            out[f"render {width}x{height}"] = _median_ms(
                lambda: sim.world.render(width, height, view, camera.projection), frames
            )
            out[f"frame {width}x{height}"] = _median_ms(lambda: camera.capture(optical), frames)
        out["lidar scan"] = _median_ms(lambda: sim.capture("scout"), frames)
        return out
    finally:
        sim.close()


def _in_child(fn, *args):
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        return pool.apply(fn, args)


def bench_sensors(frames):
    fast = _in_child(_sensor_costs, "fast", frames)
    pybullet = {r: _in_child(_sensor_costs, r, frames) for r in ("egl", "tiny")}
    assert fast["renderer"] == "fast", "the fast renderer fell back to PyBullet's: see the log above"
    print(f"\n== Sensor costs, median of {frames}, ms (each renderer in its own process) ==")
    print(f"{'what':34s} {'fast':>8s} {'PyBullet':>9s} {'PyBullet x':>11s} {'target':>7s}")
    rows = []
    for width, height in FRAME_SIZES:
        ref = PYBULLET_FOR_SIZE[width]
        rows.append(
            (
                f"render() {width}x{height} ({ref})",
                fast[f"render {width}x{height}"],
                pybullet[ref][f"render {width}x{height}"],
                ">= 5" if width == 640 else "",
            )
        )
        rows.append(
            (
                f"  + depth, cloud {width}x{height}",
                fast[f"frame {width}x{height}"],
                pybullet[ref][f"frame {width}x{height}"],
                "",
            )
        )
    rows.append(("lidar scan 16x1875 (rayTestBatch)", fast["lidar scan"], pybullet["egl"]["lidar scan"], ">= 10"))
    for label, ours, theirs, target in rows:
        print(f"{label:34s} {ours:8.1f} {theirs:9.1f} {theirs / ours:11.1f} {target:>7s}")
    return rows


def run_sensor_loop(profile, renderer, seconds, workers, warmup_s=4.0):
    """Drive the sensor worker pool as fleet_sim does (EDF over the configured rates) with the
    robots at their sample poses; (core-seconds per second, {robot: (configured Hz, achieved Hz)})."""
    from multiprocessing.connection import wait

    from cps_fleet.fleet import load_fleet
    from cps_fleet.site import load_site
    from cps_sim.sample_clouds import SAMPLE_POSES
    from cps_sim.scheduling import SensorScheduler
    from cps_sim.sensor_workers import SensorWorkerPool
    from cps_sim.simulation import FleetSimulation

    fleet = load_fleet(profile=profile)
    site = load_site(fleet.site_path)
    sim = FleetSimulation(fleet, site=site, renderer=None)
    for name, (x, y, z, yaw_deg) in SAMPLE_POSES.items():
        sim.place(name, x, y, z, math.radians(yaw_deg))
    pool = SensorWorkerPool(fleet, site, renderer, workers)
    in_force = pool.renderer
    try:
        now = time.time()
        scheduler = SensorScheduler({n: s.rate_hz for n, s in sim.robots.items()}, now)
        counts = {name: 0 for name in sim.robots}
        measuring_from = now + warmup_s
        stop_at = measuring_from + seconds
        cpu_start = parent_start = None
        while True:
            now = time.time()
            if cpu_start is None and now >= measuring_from:
                parent_start = time.process_time()
                cpu_start = parent_start + sum(process_cpu_s(w.process.pid) for w in pool.workers)
                counts = {name: 0 for name in sim.robots}
            if now >= stop_at:
                break
            worked = False
            for name, _frame, requested, _started, _finished in pool.results():
                scheduler.done(name, requested, time.time())
                counts[name] += 1
                worked = True
            while True:
                worker = pool.idle_worker()
                if worker is None:
                    break
                name, due = scheduler.next(exclude=[w.busy_with for w in pool.workers if w.busy_with])
                if name is None or due > now:
                    break
                pool.request(worker, name, sim.poses(), time.time())
                worked = True
            if not worked:
                _, next_due = scheduler.next(exclude=[w.busy_with for w in pool.workers if w.busy_with])
                pause_s = min(max(next_due - time.time(), 0.0), 0.01)
                busy = [w.conn for w in pool.workers if w.busy_with]
                if busy:
                    wait(busy, timeout=pause_s)
                else:
                    time.sleep(pause_s)
        parent_s = time.process_time() - parent_start
        cpu_s = parent_s + sum(process_cpu_s(w.process.pid) for w in pool.workers) + parent_start - cpu_start
    finally:
        pool.close()
    rates = {name: (s.rate_hz, counts[name] / seconds) for name, s in sim.robots.items()}
    return in_force, cpu_s / seconds, parent_s / seconds, rates


def bench_fleet_cpu(seconds, workers):
    print(
        f"\n== Light profile, sensors at their configured rates, {workers} worker processes, "
        f"{seconds:.0f} s measured: core-seconds per mission-second (this process + workers) =="
    )
    results = {}
    for renderer in ("fast", "auto"):
        in_force, core_s, parent_core_s, rates = run_sensor_loop("light", renderer, seconds, workers)
        # A renderer that misses its rates also spends less: scale to the configured captures.
        scale = sum(c for c, _ in rates.values()) / max(sum(a for _, a in rates.values()), 1e-9)
        results[renderer] = core_s * scale
        achieved = ", ".join(f"{n} {a:.1f}/{c:.0f} Hz" for n, (c, a) in rates.items())
        print(
            f"{renderer:5s} (in force: {in_force:4s}) {core_s:5.2f} core-s/s measured (scheduling process "
            f"{parent_core_s:.2f}), {core_s * scale:5.2f} at the configured rates   {achieved}"
        )
    print(f"fast / PyBullet at the configured rates: {100 * results['fast'] / results['auto']:.0f} % (target <= 30 %)")
    return results


def bench_paper_rates(seconds, workers):
    print(f"\n== Paper profile, sensors alone, fast renderer, {workers} worker processes, {seconds:.0f} s ==")
    in_force, core_s, parent_core_s, rates = run_sensor_loop("paper", "fast", seconds, workers)
    captures_per_s = sum(achieved for _, achieved in rates.values())
    configured_per_s = sum(configured for configured, _ in rates.values())
    print(
        f"renderer in force {in_force}, {core_s:.2f} core-s/s (of which scheduling process {parent_core_s:.2f}) "
        f"for {captures_per_s:.1f} captures/s: the configured {configured_per_s:.0f} captures/s would need "
        f"~{core_s * configured_per_s / max(captures_per_s, 1e-9):.1f} cores at that cost per capture"
    )
    print(f"{'robot':8s} {'configured Hz':>13s} {'achieved Hz':>11s} {'ratio':>6s} (target >= 0.60)")
    for name, (configured, achieved) in rates.items():
        print(f"{name:8s} {configured:13.1f} {achieved:11.2f} {achieved / configured:6.2f}")
    return rates


def bench_node(seconds, workers):
    """The real fleet_sim node per renderer, light profile: rates received by a subscriber."""
    import threading

    from cps_fleet.fleet import load_fleet
    from cps_harness.testing import RosGraph

    graph = RosGraph()
    graph.start()
    os.environ.update(ROS_MASTER_URI=graph.uri, ROS_IP="127.0.0.1", ROS_HOME=graph.home)
    import rospy

    graph.point_this_process_here()
    rospy.init_node("sim_bench", anonymous=True, disable_signals=True)
    fleet = load_fleet(profile="light")
    try:
        for renderer in ("fast", "auto"):
            counts, lock, measuring = {}, threading.Lock(), threading.Event()

            def counter(topic):
                def on_msg(_msg):
                    if measuring.is_set():
                        with lock:
                            counts[topic] = counts.get(topic, 0) + 1

                return on_msg

            node_graph = graph.attach()
            node_graph.start_node(
                "cps_sim",
                "fleet_sim",
                name=f"fleet_sim_{renderer}",
                params={"~profile": "light", "~sensor_workers": workers, "~renderer": renderer},
            )
            subs = []
            try:
                node_graph.wait_for_topic(names.absolute(names.robot_topic("scout", names.POINTS)), timeout_s=120)
                subs = [
                    rospy.Subscriber(
                        names.robot_topic(r.name, names.POINTS), rospy.AnyMsg, counter(r.name), queue_size=2
                    )
                    for r in fleet.robots
                ]
                time.sleep(5.0)
                measuring.set()
                time.sleep(seconds)
                measuring.clear()
            finally:
                for sub in subs:
                    sub.unregister()
                node_graph.close()
            print(
                f"fleet_sim node, light, renderer {renderer}: "
                + ", ".join(f"{r.name} {counts.get(r.name, 0) / seconds:.1f} Hz" for r in fleet.robots)
            )
    finally:
        rospy.signal_shutdown("bench done")
        graph.close()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=15, help="frames/scans per sensor measurement")
    parser.add_argument("--seconds", type=float, default=20.0, help="measuring time per fleet run, s")
    parser.add_argument("--workers", type=int, default=2, help="sensor worker processes")
    parser.add_argument("--node", action="store_true", help="also run the fleet_sim node per renderer")
    args = parser.parse_args(argv)
    # As in SensorWorkerPool's workers: one BLAS thread, so the cost children measure what the
    # workers pay (OpenBLAS's spinning threads would otherwise be counted, or compete).
    os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    print(
        f"cps_sim benchmark on {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start, "
        f"{time.strftime('%Y-%m-%d %H:%M')}"
    )
    bench_sensors(args.frames)
    bench_fleet_cpu(args.seconds, args.workers)
    bench_paper_rates(args.seconds, args.workers)
    if args.node:
        bench_node(args.seconds, args.workers)
    print(f"\nload average at end {os.getloadavg()[0]:.1f} (other processes share these cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
