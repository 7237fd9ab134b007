"""What today's process layout does with a larger fleet: loopback missions (`cps_bringup all`) of
each fleet file, against the four-robot fleet.yaml as the anchor in the same run.

Per fleet: the processes the mission runs, the cores its process tree uses in the steady state
(sampled from /proc every 5 s), the machine's load, and per robot the achieved sensor rate on the
robots' side (physical_stats.csv), the managed rate at the twin and odometry at the twin
(stats.csv), over the mission's window (from the first odometry at the twin + 5 s, `--duration`
long less those 5 s). Not part of `make bench` (a 16-robot mission takes ~8 minutes with its
shutdown); figures into docs/benchmarks/fleet_size.md.

    python bench/fleet_size.py [--fleets fleet.yaml,fleets/fleet16.yaml] [--duration 40] [--out DIR]
"""

import argparse
import collections
import csv
import json
import os
import re
import tempfile
import threading
import time

from cps_fleet import names

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONFIG = os.path.join(ROOT, "catkin_ws", "src", "cps_bringup", "config")
HZ = os.sysconf("SC_CLK_TCK")
SAMPLE_S = 5.0
# topic_stats' ~window_s as cps_bringup runs it (its default).
STATS_WINDOW_S = 2.0


def _tree(root):
    kids = collections.defaultdict(list)
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as stream:
                kids[int(stream.read().rsplit(")", 1)[1].split()[1])].append(int(pid))
        except OSError:
            pass
    out, stack = [], [root]
    while stack:
        pid = stack.pop()
        out.append(pid)
        stack += kids.get(pid, [])
    return out


def _kind(pid):
    """The node's name without its robot (velocity_mux, draco_decoder...), or the program's."""
    try:
        with open(f"/proc/{pid}/cmdline") as stream:
            argv = stream.read().split("\0")
    except OSError:
        return None
    for arg in argv:
        if arg.startswith("__name:="):
            return re.sub(r"^[a-z]+_\d+_", "", arg[len("__name:=") :])
    line = " ".join(argv)
    for key, name in (
        ("rosmaster", "rosmaster"),
        ("zenoh_bridge", "zenoh_bridge"),
        ("spawn_main", "sensor_worker"),
        ("rosout", "rosout"),
        ("cps_bringup", "cps_bringup"),
    ):
        if key in line:
            return name
    return os.path.basename(argv[0]) if argv and argv[0] else "other"


def _cpu_s(pid):
    try:
        with open(f"/proc/{pid}/stat") as stream:
            fields = stream.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / HZ
    except OSError:
        return None


class TreeSampler(threading.Thread):
    """Every SAMPLE_S: processes in the tree under `root` and the cores each kind of them used."""

    def __init__(self, root):
        super().__init__(daemon=True)
        self.root, self.samples = root, []

    def run(self):
        previous, then = {}, time.monotonic()
        while os.path.exists(f"/proc/{self.root}"):
            time.sleep(SAMPLE_S)
            now = time.monotonic()
            by_kind, current = collections.Counter(), {}
            for pid in _tree(self.root):
                cpu, kind = _cpu_s(pid), _kind(pid)
                if cpu is None or kind is None:
                    continue
                current[pid] = cpu
                by_kind[kind] += (cpu - previous.get(pid, cpu)) / (now - then)
            with open("/proc/loadavg") as stream:
                load = float(stream.read().split()[0])
            self.samples.append(
                {"t": now, "procs": len(current), "cores": sum(by_kind.values()), "load": load, "by": by_kind}
            )
            previous, then = current, now


def _per_topic(path):
    topics = collections.OrderedDict()
    with open(path) as stream:
        for row in csv.DictReader(stream):
            topics.setdefault(row["topic"], []).append((float(row["time_s"]), int(row["messages"])))
    return topics


def run_fleet(fleet_file, duration_s, out_dir):
    from cps_fleet.fleet import load_fleet

    fleet = load_fleet(fleet_file)
    from cps_harness.mission import Mission

    started = time.monotonic()
    log_path = os.path.join(out_dir, "bringup.log")
    with Mission(
        os.path.join(out_dir, "mission"), ["--fleet", fleet_file, "--duration", duration_s], log_path=log_path
    ) as mission:
        sampler = TreeSampler(mission.pid)
        sampler.start()
        mission.wait_until_up()
        ended = r"duration of .* reached"
        mission.wait_for(ended, duration_s + 120)
        up_at, ended_at = mission.up_at, mission.seen[ended]
        mission.finish()
    sampler.join(timeout=SAMPLE_S * 2)
    finished = time.monotonic()
    out_dir = os.path.join(out_dir, "mission")
    # The steady state: from 10 s after every process is up to the end of the mission.
    steady = [s for s in sampler.samples if up_at + 10.0 < s["t"] <= ended_at] or sampler.samples
    up = max(s["procs"] for s in steady)
    by_kind = collections.Counter()
    for sample in steady:
        for kind, cores in sample["by"].items():
            by_kind[kind] += cores / len(steady)
    physical, twin = (
        _per_topic(os.path.join(out_dir, "physical_stats.csv")),
        _per_topic(os.path.join(out_dir, "stats.csv")),
    )
    first_odom = min(t for topic, rows in twin.items() if topic.endswith("/" + names.ODOM) for t, n in rows if n > 0)
    t0, t1 = first_odom + 5.0, first_odom + duration_s

    def rate(rows):
        """Messages per second: each stats row counts the messages of its last STATS_WINDOW_S (rows
        overlap, and the rows' rate_hz, (n-1)/span, jumps on bursts)."""
        inside = [n for t, n in rows if t0 < t <= t1]
        return sum(inside) / len(inside) / STATS_WINDOW_S if inside else 0.0

    robots = []
    for robot in fleet.robots:
        sensor = "lidar" if robot.has_lidar else "depth"
        configured = fleet.profile.lidar.rate_hz if robot.has_lidar else fleet.profile.depth_camera.rate_hz
        robots.append(
            {
                "robot": robot.name,
                "sensor": sensor,
                "configured_hz": configured,
                "robots_side_hz": rate(
                    physical.get(names.absolute(names.robot_topic(robot.name, names.POINTS_FILTERED)), [])
                ),
                "twin_managed_hz": rate(twin.get(names.absolute(names.managed_cloud_at_twin(robot.name)), [])),
                "odom_at_twin_hz": rate(twin.get(names.absolute(names.robot_topic(robot.name, names.ODOM)), [])),
            }
        )
    return {
        "fleet": os.path.relpath(fleet_file, CONFIG),
        "robots": len(fleet.robots),
        "exit_code": mission.returncode,
        "processes_up": up,
        "cores": sum(s["cores"] for s in steady) / len(steady),
        "load": [s["load"] for s in steady],
        "by_kind": dict(by_kind.most_common()),
        "per_robot": robots,
        "all_robots_up": all(r["robots_side_hz"] > 0 and r["twin_managed_hz"] > 0 for r in robots),
        "shutdown_s": finished - ended_at if ended_at else None,
        "wall_s": finished - started,
    }


def _mean(values):
    values = list(values)
    return sum(values) / len(values) if values else float("nan")


def report(results):
    anchor = results[0]
    print(
        "| fleet | robots | all up | processes | cores (of 2) | sensor Hz per robot, robots' side: lidar / depth "
        "(configured 5 / 10) | twin managed Hz | odom at twin Hz (50) | shutdown s |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        lidar = [x["robots_side_hz"] for x in r["per_robot"] if x["sensor"] == "lidar"]
        depth = [x["robots_side_hz"] for x in r["per_robot"] if x["sensor"] == "depth"]
        print(
            f"| {r['fleet']} | {r['robots']} | {'yes' if r['all_robots_up'] else 'NO'} | {r['processes_up']} | "
            f"{r['cores']:.2f} | {_mean(lidar):.2f} / {_mean(depth):.2f} | "
            f"{_mean(x['twin_managed_hz'] for x in r['per_robot']):.2f} | "
            f"{_mean(x['odom_at_twin_hz'] for x in r['per_robot']):.1f} | {r['shutdown_s'] or float('nan'):.0f} |"
        )
    for r in results[1:]:
        ratio = _mean(x["robots_side_hz"] for x in r["per_robot"]) / _mean(
            x["robots_side_hz"] for x in anchor["per_robot"]
        )
        print(
            f"\n{r['fleet']}: per-robot sensor rate {ratio:.2f}x the anchor's ({anchor['fleet']}), "
            f"{r['robots'] / anchor['robots']:.0f}x the robots, processes {r['processes_up'] / anchor['processes_up']:.1f}x"
        )
    for r in results:
        print(
            f"\n{r['fleet']}: cores by node kind (steady state): "
            + ", ".join(f"{k} {v:.2f}" for k, v in r["by_kind"].items() if v >= 0.01)
        )


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--fleets",
        default="fleet.yaml,fleets/fleet16.yaml",
        help="fleet files relative to cps_bringup/config (the first is the anchor)",
    )
    parser.add_argument("--duration", type=float, default=40.0)
    parser.add_argument("--out", default=None, help="folder for the missions' outputs (default: a new temporary one)")
    args = parser.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="cps-fleet-size-")
    os.chmod(out, 0o777)  # the nodes run as 'nobody' when the bench runs as root
    results = []
    for name in args.fleets.split(","):
        folder = os.path.join(out, re.sub(r"\W+", "_", name))
        print(f"== {name} -> {folder}", flush=True)
        results.append(run_fleet(os.path.join(CONFIG, name), args.duration, folder))
        print(json.dumps({k: v for k, v in results[-1].items() if k != "per_robot"}), flush=True)
    with open(os.path.join(out, "fleet_size.json"), "w") as stream:
        json.dump(results, stream, indent=1)
    report(results)


if __name__ == "__main__":
    main()
