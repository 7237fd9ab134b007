#!/usr/bin/env python3
"""cps_sim benchmark: render and ray-cast costs, and the whole fleet's achieved rates.

1. ms per depth frame (640x480, 320x240, 160x120) with PyBullet's EGL plugin vs TinyRenderer, and
   ms per lidar scan (16 x 1875 rays), in this process (anchor: EGL 640x480).
2. The fleet_sim node on a private ROS master, per profile (light, paper): achieved sensor
   rates measured by a subscriber (raw messages, no deserialization) and reported by the node
   on /diagnostics, odometry rate and real-time factor (anchor: each sensor's configured rate).

Usage: python bench/sim_bench.py [--frames 10] [--seconds 20] [--profiles light,paper]
       [--workers 2] [--renderers egl,auto] [--skip-fleet]
Timings on a shared machine are noisy; run it on an idle machine for figures to quote.
"""
import argparse
import math
import os
import statistics
import sys
import threading
import time


DEPTH_SIZES = ((640, 480), (320, 240), (160, 120))


def _median_ms(fn, repeats):
    """(median wall ms, min wall ms, median CPU ms of this process, all threads)."""
    fn()  # warm-up (first EGL frame compiles shaders)
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(1000.0 * (time.perf_counter() - start))
        cpu.append(1000.0 * (time.process_time() - start_cpu))
    return statistics.median(wall), min(wall), statistics.median(cpu)


def bench_sensors(frames):
    from cps_fleet.fleet import load_fleet
    from cps_sim.sample_clouds import SAMPLE_POSES
    from cps_sim.sensors import DepthCamera, Lidar
    from cps_sim.simulation import FleetSimulation

    fleet = load_fleet(profile="paper")
    cam_cfg, lidar_cfg = fleet.profile.depth_camera, fleet.profile.lidar
    results = {}
    for renderer in ("egl", "tiny"):
        sim = FleetSimulation(fleet, renderer=renderer)
        try:
            for name, pose in SAMPLE_POSES.items():
                x, y, z, yaw = pose
                sim.place(name, x, y, z, math.radians(yaw))
            optical = sim.robots["jackal"].robot.sensor_in_map()
            for width, height in DEPTH_SIZES:
                camera = DepthCamera(sim.world, width, height, cam_cfg.hfov_deg, cam_cfg.near_m, cam_cfg.far_m)
                results[(renderer, width)] = _median_ms(lambda: camera.capture(optical), frames)
            if renderer == "egl":
                lidar = sim.robots["scout"].sensor
                assert isinstance(lidar, Lidar)
                pose = sim.robots["scout"].robot.sensor_in_map()
                results["lidar"] = _median_ms(lambda: lidar.capture(pose), frames)
        finally:
            sim.close()
    anchor = results[("egl", 640)][0]
    print("\n== Sensor costs (median of %d, this process; anchor EGL 640x480 = %.1f ms) ==" % (frames, anchor))
    print(f"{'what':34s} {'median ms':>10s} {'min ms':>8s} {'CPU ms':>8s} {'x anchor':>9s}")
    for renderer in ("egl", "tiny"):
        for width, height in DEPTH_SIZES:
            med, low, cpu = results[(renderer, width)]
            label = f"depth frame {width}x{height} {'EGL' if renderer == 'egl' else 'TinyRenderer'}"
            print(f"{label:34s} {med:10.1f} {low:8.1f} {cpu:8.1f} {med / anchor:9.2f}")
    med, low, cpu = results["lidar"]
    rays = lidar_cfg.rings * lidar_cfg.samples_per_ring
    print(f"{'lidar scan (%d rays)' % rays:34s} {med:10.1f} {low:8.1f} {cpu:8.1f} {med / anchor:9.2f}")
    return results


def bench_fleet(profile, seconds, workers, renderer):
    import rospy
    from diagnostic_msgs.msg import DiagnosticArray

    from cps_fleet.fleet import load_fleet

    fleet = load_fleet(profile=profile)
    counts = {}
    lock = threading.Lock()
    measuring = threading.Event()

    def counter(topic):
        def on_msg(_msg):
            if measuring.is_set():
                with lock:
                    counts[topic] = counts.get(topic, 0) + 1
        return on_msg

    last_diag = {}

    def on_diag(msg):
        last_diag["msg"] = msg

    graph = _GRAPH.attach()
    graph.start_node("cps_sim", "fleet_sim", name=f"fleet_sim_{profile}",
                            params={"~profile": profile, "~sensor_workers": workers, "~renderer": renderer})
    subs = []
    try:
        graph.wait_for_topic("/scout/points", timeout_s=120)
        topics = [f"/{r.name}/points" for r in fleet.robots] + [f"/{r.name}/odom" for r in fleet.robots]
        subs = [rospy.Subscriber(t, rospy.AnyMsg, counter(t), queue_size=2) for t in topics]
        subs.append(rospy.Subscriber("/diagnostics", DiagnosticArray, on_diag, queue_size=2))
        time.sleep(8.0)  # warm-up: workers compile shaders, connections settle
        measuring.set()
        start = time.monotonic()
        time.sleep(seconds)
        elapsed = time.monotonic() - start
        measuring.clear()
        diag = last_diag.get("msg")
    finally:
        for sub in subs:
            sub.unregister()
        graph.close()
    reported = {}
    rtf = float("nan")
    if diag is not None:
        for status in diag.status:
            values = {kv.key: kv.value for kv in status.values}
            if status.name == "cps_sim: fleet":
                rtf = float(values["real_time_factor"])
            elif "achieved_hz" in values:
                reported[status.hardware_id] = (float(values["achieved_hz"]), float(values["capture_ms"]))
    print(f"\n== Fleet, profile '{profile}', renderer '{renderer}' ({workers} sensor worker(s), {seconds:.0f} s measured; "
          f"anchor: configured rate) ==")
    print(f"{'robot':8s} {'sensor':22s} {'configured':>10s} {'received':>9s} {'reported':>9s} {'ratio':>6s} "
          f"{'capture ms':>10s} {'odom Hz':>8s}")
    rows = []
    for robot in fleet.robots:
        if robot.has_lidar:
            lp = fleet.profile.lidar
            sensor, rate = f"lidar {lp.rings}x{lp.samples_per_ring}", lp.rate_hz
        else:
            cp = fleet.profile.depth_camera
            sensor, rate = f"rgbd {cp.width}x{cp.height}", cp.rate_hz
        received = counts.get(f"/{robot.name}/points", 0) / elapsed
        odom = counts.get(f"/{robot.name}/odom", 0) / elapsed
        rep, cap = reported.get(robot.name, (float("nan"), float("nan")))
        rows.append((robot.name, rate, received))
        print(f"{robot.name:8s} {sensor:22s} {rate:10.1f} {received:9.2f} {rep:9.2f} {received / rate:6.2f} "
              f"{cap:10.1f} {odom:8.1f}")
    print(f"real-time factor (reported by fleet_sim): {rtf:.3f}")
    return rows, rtf


_GRAPH = None


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10, help="frames/scans per sensor measurement")
    parser.add_argument("--seconds", type=float, default=20.0, help="measuring time per fleet profile, s")
    parser.add_argument("--profiles", default="light,paper", help="comma list of fleet profiles")
    parser.add_argument("--workers", type=int, default=2, help="fleet_sim ~sensor_workers")
    parser.add_argument("--renderers", default="egl,auto", help="comma list of fleet_sim ~renderer values to run")
    parser.add_argument("--skip-fleet", action="store_true", help="only the per-sensor costs")
    args = parser.parse_args(argv)
    print(f"cps_sim benchmark on {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start")
    bench_sensors(args.frames)
    if args.skip_fleet:
        return 0
    global _GRAPH
    from cps_harness.testing import RosGraph

    _GRAPH = RosGraph()
    _GRAPH.start()
    os.environ.update(ROS_MASTER_URI=_GRAPH.uri, ROS_IP="127.0.0.1", ROS_HOME=_GRAPH.home)
    import rospy

    _GRAPH.point_this_process_here()
    rospy.init_node("sim_bench", anonymous=True, disable_signals=True)
    try:
        for renderer in [r.strip() for r in args.renderers.split(",") if r.strip()]:
            for profile in [p.strip() for p in args.profiles.split(",") if p.strip()]:
                bench_fleet(profile, args.seconds, args.workers, renderer)
    finally:
        rospy.signal_shutdown("bench done")
        _GRAPH.close()
    print(f"\nload average at end {os.getloadavg()[0]:.1f} (other processes share these cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
