"""Bandwidth manager benchmarks.

1. Solve time of `allocate_frequencies` (exact water-filling) for 4 to 1000 managed topics, against
   the anchor measured in the same run: scipy's linprog (HiGHS) on the Eq. 1 LP
   (maximize sum w_i s_i f_i  s.t.  sum s_i f_i <= B, fmin <= f <= fmax), the paper's formulation.
   Goal: < 10 ms at 100 topics.
2. Time from a priority change (/tissue/set_priority) to the new rates being in force at the rate
   limiters (cps_transport's rate_limiter reports its set rate on ~status right after a change),
   on a private loopback master, and over the shaped 60 Mbit/s link under the Table 6 load
   (needs root; skipped with the reason otherwise).

    python bench/allocator_bench.py [--repeats 50] [--skip-ros]
"""

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
from scipy.optimize import linprog
from timing import median_max_ms

from cps_bw_manager.allocation import RobotDemand, allocate_frequencies
from cps_fleet import names


def _fleet(n, rng):
    sizes = rng.uniform(10000, 150000, n)
    priorities = rng.integers(0, 2, n)
    return [RobotDemand(f"r{i}", float(sizes[i]), int(priorities[i]), 1.0, 30.0) for i in range(n)]


def _lp(demands, budget):
    size = np.array([d.message_bytes for d in demands]) / 1e6
    weight = np.array([4.0 if d.priority else 1.0 for d in demands])
    return linprog(
        -(weight * size),
        A_ub=[size],
        b_ub=[budget],
        bounds=[(d.min_rate_hz, d.max_rate_hz) for d in demands],
        method="highs",
    )


def bench_solve(repeats):
    rng = np.random.default_rng(1)
    print("solve time (median / max of %d runs, ms); budget = half of what all robots at 30 Hz need" % repeats)
    print(f"{'topics':>7} {'water-filling':>16} {'linprog HiGHS (anchor)':>24} {'ratio':>7}")
    rows = []
    for n in (4, 10, 100, 1000):
        demands = _fleet(n, rng)
        budget = 0.5 * sum(d.message_bytes * 30.0 for d in demands) / 1e6
        ours = median_max_ms(lambda: allocate_frequencies(demands, budget), repeats)
        anchor = median_max_ms(lambda: _lp(demands, budget), max(5, repeats // 5))
        rows.append((n, ours, anchor))
        print(
            f"{n:>7} {ours[0]:8.3f} / {ours[1]:6.3f} {anchor[0]:12.3f} / {anchor[1]:8.3f} {anchor[0] / ours[0]:7.1f}x"
        )
    at_100 = next(o for n, o, _ in rows if n == 100)[0]
    print(f"goal < 10 ms at 100 topics: {'met' if at_100 < 10 else 'NOT met'} ({at_100:.3f} ms)")
    return rows


def measure_priority_to_rate(changes, robots, feed):
    """Seconds from each set_priority call returning to every limiter reporting the new
    allocation's rate. Needs a running graph (manager + limiters) and rospy initialised."""
    import rospy

    from cps_msgs.msg import BandwidthAllocationArray, CompressedPointCloud2, RateLimiterStatus
    from cps_msgs.srv import SetPriority

    set_rates, latest_alloc = {}, {}
    changed = threading.Condition()

    def on_status(msg, robot):
        with changed:
            set_rates[robot] = msg.set_rate_hz
            changed.notify_all()

    def on_alloc(msg):
        with changed:
            latest_alloc.update({a.robot: a.rate_hz for a in msg.allocations if a.stream == "cloud"})
            changed.notify_all()

    subs = [
        rospy.Subscriber(names.robot_topic(r, names.LIMITER_STATUS), RateLimiterStatus, on_status, callback_args=r)
        for r in robots
    ]
    subs.append(rospy.Subscriber(names.ALLOCATION, BandwidthAllocationArray, on_alloc))
    stop = threading.Event()
    if feed:
        pubs = {
            r: rospy.Publisher(names.robot_topic(r, names.POINTS_DRACO), CompressedPointCloud2, queue_size=2)
            for r in robots
        }

        def feeder():
            msg = CompressedPointCloud2(compressed_data=bytes(30000))
            while not stop.is_set():
                for pub in pubs.values():
                    msg.header.stamp = rospy.Time.now()
                    pub.publish(msg)
                time.sleep(0.05)

        threading.Thread(target=feeder, daemon=True).start()
    rospy.wait_for_service(names.SET_PRIORITY, timeout=60)
    time.sleep(5.0)  # sizes measured
    proxy = rospy.ServiceProxy(names.SET_PRIORITY, SetPriority)
    delays = []
    for k in range(changes):
        with changed:
            before = dict(set_rates)
        t0 = time.monotonic()
        proxy(robot=robots[0], priority=(k + 1) % 2)
        with changed:
            done = changed.wait_for(
                lambda: (
                    set_rates.get(robots[0]) != before.get(robots[0])
                    and all(r in latest_alloc and abs(set_rates.get(r, -1) - latest_alloc[r]) < 1e-6 for r in robots)
                ),
                timeout=5.0,
            )
        if done:
            delays.append(time.monotonic() - t0)
        time.sleep(0.3)
    stop.set()
    for sub in subs:
        sub.unregister()
    return delays


def _report(label, delays, changes):
    if not delays:
        print(f"{label}: no change observed")
        return
    print(
        f"{label}: median {1000 * statistics.median(delays):.0f} ms, max {1000 * max(delays):.0f} ms "
        f"over {len(delays)}/{changes} changes (goal: within 1 s)"
    )


def bench_priority_to_rate(changes):
    """On a private loopback master: manager + two rate limiters fed from this process."""
    import rospy

    from cps_harness.testing import RosGraph

    robots = ("scout", "jackal")
    with RosGraph() as graph:
        for r in robots:
            graph.start_node(
                "cps_transport",
                "rate_limiter",
                name=names.CLOUD_THROTTLE,
                namespace=names.absolute(r),
                remap={
                    names.INPUT: names.absolute(names.robot_topic(r, names.POINTS_DRACO)),
                    names.OUTPUT: names.absolute(names.managed_cloud(r)),
                },
            )
        graph.start_node(
            "cps_bw_manager",
            "bandwidth_manager",
            name="bandwidth_manager",
            params={"~robots": list(robots), "~available_mbps": 4.0},
        )
        graph.wait_for_service(names.absolute(names.SET_PRIORITY), timeout_s=60)
        graph.point_this_process_here()
        rospy.init_node("allocator_bench", anonymous=True, disable_signals=True)
        delays = measure_priority_to_rate(changes, robots, feed=True)
        rospy.signal_shutdown("bench done")
    _report("priority change -> new rates in force at both limiters (loopback)", delays, changes)
    return delays


def bench_priority_to_rate_on_link(changes):
    """Over the shaped 60 Mbit/s link: limiters and the Table 6 load on the physical side, the
    manager and this measurement on the digital twin, so the new rate crosses the link."""
    import json

    from cps_harness.link_run import LinkRosGraph
    from cps_link.netns_link import LinkError, ShapedLink, check_capability
    from cps_ros.processes import find_node

    try:
        check_capability()
    except LinkError as exc:
        print(f"priority change over the shaped link: skipped ({exc})")
        return None
    robots = ("scout", "jackal", "champ", "iris")
    load = find_node("cps_harness", "cloud_load")
    with ShapedLink("cpsbench") as link, LinkRosGraph(link) as graph:
        limiter = find_node("cps_transport", "rate_limiter")
        for r in robots:
            graph.start_python(
                "phys",
                limiter,
                [
                    f"__name:={names.CLOUD_THROTTLE}",
                    f"__ns:={names.absolute(r)}",
                    f"{names.INPUT}:={names.absolute(names.robot_topic(r, names.POINTS_DRACO))}",
                    f"{names.OUTPUT}:={names.absolute(names.managed_cloud(r))}",
                ],
                name=f"limiter_{r}",
            )
        graph.start_python(
            "phys", load, ["scout:34000:10", "jackal:142000:30", "champ:60000:30", "iris:67000:30"], name="load"
        )
        graph.start_python(
            "twin",
            find_node("cps_bw_manager", "bandwidth_manager"),
            ["__name:=bandwidth_manager", "_available_mbps:=55.0"],
            name="manager",
        )
        result = subprocess.run(
            link.argv(
                "twin",
                [
                    sys.executable,
                    os.path.abspath(__file__),
                    "--measure-only",
                    "--changes",
                    str(changes),
                    "--robots",
                    ",".join(robots),
                ],
                master_port=graph.port,
            ),
            capture_output=True,
            text=True,
            timeout=120,
        )
    try:
        delays = json.loads(result.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        print(f"priority change over the shaped link: failed: {result.stderr[-1000:]}")
        return None
    _report(
        "priority change -> new rates in force at all four limiters (over the 60 Mbit/s link, loaded)", delays, changes
    )
    return delays


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--changes", type=int, default=20)
    parser.add_argument("--skip-ros", action="store_true")
    parser.add_argument("--measure-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--robots", default="scout,jackal", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure_only:  # run inside the digital-twin namespace by bench_priority_to_rate_on_link
        import json

        import rospy

        rospy.init_node("allocator_bench", anonymous=True, disable_signals=True)
        print(json.dumps(measure_priority_to_rate(args.changes, tuple(args.robots.split(",")), feed=False)))
        rospy.signal_shutdown("done")
        return
    print("(2 shared cores, other jobs running: timings are noisy)")
    bench_solve(args.repeats)
    if not args.skip_ros:
        bench_priority_to_rate(args.changes)
        bench_priority_to_rate_on_link(args.changes)


if __name__ == "__main__":
    main()
