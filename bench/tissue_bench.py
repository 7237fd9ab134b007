"""The tissue's CPU per robot per cloud rate: one process per node and robot (the executables run
until now: `nodelet load`, draco_encoder, rate_limiter, image_compressor, draco_decoder,
backfill decoder) against the shared layout (one voxel_grid_loader, one cloud_tissue, one
cloud_decoder), measured in the same run on a private master.

Both layouts are the bringup's own plan (`plan_nodes(..., tissue_layout=...)`, Zenoh transport):
the nodelet manager with the real pcl/VoxelGrid, the encoders, limiters (set to let every cloud
through), JPEG compressors (idle: no one watches) and decoders. This process stands in for the
simulator and the Zenoh bridges: it publishes every robot's synthetic cloud (cps_harness, the
light profile: 16 x 1875 lidar, 160 x 120 depth) at a fixed rate and relays each managed cloud
to the twin's topic; it is not measured. CPU = user + system time of every tissue process and
its children (/proc), summed over a fixed window once clouds arrive on every twin topic; the
layouts alternate (A B A B) so that a noisy neighbour hits both.

    python bench/tissue_bench.py [--copies 1] [--rate-hz 5] [--window-s 20] [--rounds 2]
"""

import argparse
import os
import sys
import tempfile
import threading
import time

from cps_fleet import names

TICKS_PER_S = os.sysconf("SC_CLK_TCK")


def _proc_stat(pid):
    """(ppid, cpu seconds, rss bytes) of a process from /proc, or None when it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as stream:
            fields = stream.read().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    # After the name: state ppid ... utime (field 14) stime (15) ... rss (24), 1-based from pid.
    cpu_s = (int(fields[11]) + int(fields[12])) / TICKS_PER_S
    return int(fields[1]), cpu_s, int(fields[21]) * os.sysconf("SC_PAGE_SIZE")


def process_tree(roots):
    """Every live pid among `roots` and their descendants."""
    parents = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            stat = _proc_stat(int(name))
            if stat:
                parents.setdefault(stat[0], []).append(int(name))
    out, todo = set(), list(roots)
    while todo:
        pid = todo.pop()
        if pid not in out and _proc_stat(pid):
            out.add(pid)
            todo += parents.get(pid, [])
    return out


def cpu_and_rss(pids):
    stats = [s for s in (_proc_stat(p) for p in pids) if s]
    return {p: s[1] for p, s in zip(pids, stats)}, sum(s[2] for s in stats)


class Feeder:
    """Publishes each robot's cloud at `rate_hz` and relays /<r>/.../managed to /twin/<r>/.../managed
    (the bridges' part); counts the decoded clouds on /twin/<r>/points."""

    def __init__(self, fleet, rate_hz):
        import rospy
        from sensor_msgs.msg import PointCloud2

        from cps_harness.synthetic_clouds import depth_camera_cloud, lidar_cloud
        from cps_ros.relay import relay_class, relay_message

        profile = fleet.profiles["light"]
        self.rate_hz = rate_hz
        self.clouds, self.pubs, self.relays, self.subs = {}, {}, [], []
        self.decoded = {r: 0 for r in fleet.robot_names}
        self.lock = threading.Lock()
        for i, robot in enumerate(fleet.robots):
            r = robot.name
            if robot.has_depth_camera:
                cam = profile.depth_camera
                cloud = depth_camera_cloud(
                    cam.width, cam.height, cam.hfov_deg, cam.far_m, seed=i, frame_id=f"{r}/{robot.sensor_frame}"
                )
            else:
                lid = profile.lidar
                cloud = lidar_cloud(
                    lid.rings,
                    lid.samples_per_ring,
                    lid.vertical_fov_deg,
                    lid.max_range_m,
                    seed=i,
                    frame_id=f"{r}/{robot.sensor_frame}",
                )
            self.clouds[r] = cloud
            self.pubs[r] = rospy.Publisher(names.robot_topic(r, robot.cloud_topic), PointCloud2, queue_size=2)
            twin = {}

            def relay(msg, twin=twin, r=r):
                if "pub" not in twin:
                    twin["cls"] = relay_class(msg._connection_header)
                    twin["pub"] = rospy.Publisher(
                        names.absolute(names.managed_cloud_at_twin(r)), twin["cls"], queue_size=5
                    )
                twin["pub"].publish(relay_message(twin["cls"], msg))

            self.relays.append(
                rospy.Subscriber(names.managed_cloud(r), rospy.AnyMsg, relay, queue_size=5, buff_size=1 << 24)
            )
            self.subs.append(
                rospy.Subscriber(
                    names.absolute(names.twin_points(r)),
                    rospy.AnyMsg,
                    self._count,
                    callback_args=r,
                    queue_size=5,
                    buff_size=1 << 24,
                )
            )
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _count(self, _msg, robot):
        with self.lock:
            self.decoded[robot] += 1

    def counts(self):
        with self.lock:
            return dict(self.decoded)

    def _run(self):
        import rospy

        period = 1.0 / self.rate_hz
        next_s = time.monotonic()
        while not self.stop.is_set():
            for r, cloud in self.clouds.items():
                cloud.header.stamp = rospy.Time.now()
                self.pubs[r].publish(cloud)
            next_s += period
            self.stop.wait(max(0.0, next_s - time.monotonic()))

    def close(self):
        self.stop.set()
        self.thread.join()
        for item in (*self.relays, *self.subs, *self.pubs.values()):
            item.unregister()


def tissue_specs(fleet, layout):
    """The tissue's processes of both sides in `layout`, as the bringup plans them."""
    from cps_bringup.plan import DIGITAL, PHYSICAL, ZENOH, RunOptions, plan_nodes

    specs = plan_nodes(
        fleet,
        sides=(PHYSICAL, DIGITAL),
        options=RunOptions(out_dir=tempfile.gettempdir(), transport=ZENOH, tissue_layout=layout),
    )
    tissue = ("nodelet_manager", "voxel_grid_loader", "cloud_tissue", "cloud_decoder")
    per_robot = (
        "voxel_grid",
        "draco_encoder",
        "cloud_throttle",
        "image_compressor",
        "draco_decoder",
        "backfill_decoder",
    )
    return [s for s in specs if s.label in tissue or s.label.split("/")[-1] in per_robot]


def measure(graph, fleet, layout, rate_hz, window_s, warmup_timeout_s=240.0):
    """Starts `layout`'s tissue, feeds it, and returns its CPU seconds, clouds decoded, processes
    and RSS over `window_s` once every robot's clouds reach the twin."""
    import rospy
    from std_msgs.msg import Float64

    from cps_harness.testing import wait_for

    procs = []
    for spec in tissue_specs(fleet, layout):
        procs.append(graph.popen(list(spec.argv), name=f"{layout}_{spec.label.replace('/', '_')}"))
        if spec.label == "nodelet_manager":
            rospy.wait_for_service(f"{names.TISSUE_NODELET_MANAGER}/load_nodelet", timeout=60)
    rates = [
        rospy.Publisher(names.robot_topic(r, names.LIMITER_RATE_HZ), Float64, queue_size=1, latch=True)
        for r in fleet.robot_names
    ]
    for pub in rates:
        pub.publish(Float64(fleet.link.max_rate_hz))
    feeder = Feeder(fleet, rate_hz)
    try:
        up = wait_for(lambda: all(feeder.counts().values()), timeout_s=warmup_timeout_s, poll_s=0.5)
        if not up:
            missing = [r for r, n in feeder.counts().items() if not n]
            logs = "\n".join(
                f"--- {p.cps_name} ({'running' if p.poll() is None else p.returncode}):\n"
                f"{graph.output(p.cps_name)[-800:]}"
                for p in procs
                if any(r in p.cps_name for r in missing) or "manager" in p.cps_name
            )
            raise RuntimeError(f"{layout}: no decoded clouds from {missing} within {warmup_timeout_s:.0f} s\n{logs}")
        time.sleep(3.0)  # the first clouds' start-up work (imports, allocations) out of the window
        pids = process_tree([p.pid for p in procs])
        cpu0, _ = cpu_and_rss(pids)
        n0 = feeder.counts()
        time.sleep(window_s)
        cpu1, rss = cpu_and_rss(pids)
        n1 = feeder.counts()
        dead = [p.cps_name for p in procs if p.poll() is not None]
        if dead:
            raise RuntimeError(f"{layout}: {', '.join(dead)} died")
        cpu_s = sum(cpu1[p] - cpu0.get(p, 0.0) for p in cpu1)
        return {
            "cpu_s": cpu_s,
            "clouds": sum(n1[r] - n0[r] for r in n1),
            "processes": len(procs),
            "pids": len(pids),
            "rss_mb": rss / 1e6,
        }
    finally:
        feeder.close()
        for pub in rates:
            pub.unregister()
        for proc in reversed(procs):
            graph.stop(proc, timeout_s=5.0)
            graph.processes.remove(proc)
        time.sleep(1.0)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--copies", type=int, default=1, help="copies of each of the 4 robots (1: 8 robots)")
    parser.add_argument("--rate-hz", type=float, default=5.0, help="clouds per second per robot")
    parser.add_argument("--window-s", type=float, default=20.0)
    parser.add_argument("--rounds", type=int, default=2, help="A/B rounds")
    args = parser.parse_args(argv)

    import rospy

    from cps_bringup.plan import PER_ROBOT, SHARED
    from cps_fleet.fleet import load_fleet
    from cps_harness.fleets import write_fleet_with_copies
    from cps_ros.processes import RosGraph

    folder = tempfile.mkdtemp(prefix="tissue_bench_")
    fleet = load_fleet(write_fleet_with_copies(folder, args.copies) if args.copies else None)
    n = len(fleet.robots)
    totals = {layout: {"cpu_s": 0.0, "clouds": 0, "window_s": 0.0} for layout in (PER_ROBOT, SHARED)}
    info = {}
    with RosGraph() as graph:
        graph.point_this_process_here()
        rospy.init_node("tissue_bench", anonymous=True, disable_signals=True)
        for round_ in range(args.rounds):
            for layout in (PER_ROBOT, SHARED):
                result = measure(graph, fleet, layout, args.rate_hz, args.window_s)
                totals[layout]["cpu_s"] += result["cpu_s"]
                totals[layout]["clouds"] += result["clouds"]
                totals[layout]["window_s"] += args.window_s
                info[layout] = result
                print(
                    f"round {round_ + 1} {layout:9s}: {result['cpu_s']:.2f} CPU-s in {args.window_s:.0f} s, "
                    f"{result['clouds']} clouds decoded, {result['processes']} processes "
                    f"({result['pids']} with children), RSS {result['rss_mb']:.0f} MB",
                    flush=True,
                )
        rospy.signal_shutdown("done")

    print(
        f"\n{n} robots, {args.rate_hz:g} Hz each (light profile clouds), "
        f"{args.rounds} x {args.window_s:.0f} s per layout"
    )
    per = {}
    for layout, t in totals.items():
        delivered_hz = t["clouds"] / t["window_s"] / n
        # CPU-seconds per second of mission, per robot, per Hz of clouds delivered = CPU-s per cloud.
        per[layout] = t["cpu_s"] / t["window_s"] / n / delivered_hz
        print(
            f"{layout:9s}: {info[layout]['processes']:3d} processes, RSS {info[layout]['rss_mb']:6.0f} MB, "
            f"{t['cpu_s'] / t['window_s']:.3f} CPU-s/s, {delivered_hz:.2f} Hz delivered per robot, "
            f"{per[layout] * 1000:.1f} ms CPU per robot per Hz"
        )
    print(
        f"shared / per_robot CPU: {per[SHARED] / per[PER_ROBOT]:.2f} "
        f"(the anchor is per_robot, today's one process per node)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
