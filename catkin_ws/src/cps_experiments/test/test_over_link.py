"""Over the real shaped link (60 Mbit/s tbf between two namespaces, TCPROS across it): four robots
publish realistic compressed clouds (Table 6 sizes) through cps_transport's rate limiters.
Manager on: every 1 s window of consumed bandwidth stays within the budget and latency p95 < 100 ms
(the paper's bound). Manager off: the same load overruns the link and latency grows. Both printed."""

import csv
import os
import time

import pytest

from cps_fleet import names
from cps_harness.link_run import LinkRosGraph, read_records, summarize
from cps_harness.testing import link_name
from cps_link import netns_link
from cps_link.netns_link import ShapedLink
from cps_ros.processes import find_node

pytestmark = [pytest.mark.ros, pytest.mark.slow]

HERE = os.path.dirname(os.path.abspath(__file__))
# robot: (mean Draco message bytes, input Hz) from Table 6 step 1 (MB/s / Hz); the lidar at 10 Hz.
LOAD = {"scout": (34000, 10.0), "jackal": (142000, 30.0), "champ": (60000, 30.0), "iris": (67000, 30.0)}
RESERVE = 0.04
PHASE_S = 8.0


def _capable():
    try:
        netns_link.check_capability()
        return None
    except netns_link.LinkError as exc:
        return str(exc)


def _set_all_rates(graph, rate_hz):
    """Stand-in for `rostopic pub` to every limiter's rate_hz topic (the manager is not running)."""
    rate_topics = [names.absolute(names.robot_topic(r, names.LIMITER_RATE_HZ)) for r in LOAD]
    code = (
        "import rospy,time; from std_msgs.msg import Float64; rospy.init_node('set_rates', anonymous=True);"
        f"pubs=[rospy.Publisher(t, Float64, queue_size=1, latch=True) for t in {rate_topics}];"
        f"time.sleep(1.5); [p.publish(Float64({rate_hz})) for p in pubs]; time.sleep(1.0)"
    )
    result = graph.run_python("twin", code)
    assert result.returncode == 0, result.stderr


def _start_load(graph, record_path=None):
    """cps_transport's rate limiters and the cloud load on the physical side, the recorder on the twin.

    Every digital-twin subscriber of a managed topic is one more TCP copy of it on the link, so
    each test has exactly one (the recorder, or topic_stats)."""
    limiter = find_node("cps_transport", "rate_limiter")
    for r in LOAD:
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
    if record_path:
        graph.start_python("twin", find_node("cps_harness", "link_recorder"), [record_path, *LOAD], name="recorder")
    graph.start_python(
        "phys",
        find_node("cps_harness", "cloud_load"),
        [f"{r}:{size}:{hz}" for r, (size, hz) in LOAD.items()],
        name="load",
    )


def _start_topic_stats(graph, stats_path, window_s):
    """cps_transport's topic_stats on the twin (one more copy of every managed topic on the link),
    publishing at 2 Hz into stats_path: the manager's estimator input."""
    graph.start_python(
        "twin",
        find_node("cps_transport", "topic_stats"),
        [
            "__name:=topic_stats",
            f"_window_s:={window_s}",
            "_publish_rate_hz:=2.0",
            f"_csv_path:={stats_path}",
            "_topics:=" + ",".join(names.absolute(names.managed_cloud(r)) for r in LOAD),
        ],
        name="topic_stats",
    )


def _wait_for_file_rows(path, timeout_s):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if os.path.exists(path) and sum(1 for _ in open(path)) > 8:
            return
        time.sleep(0.2)
    raise AssertionError(f"{path} got no rows within {timeout_s} s")


@pytest.mark.skipif(_capable() is not None, reason=f"{_capable()}")
@pytest.mark.timeout(150)
def test_manager_keeps_the_link_within_budget_and_latency_low(tmp_path):
    name = link_name("bwl")
    record_path = str(tmp_path / "received.txt")
    csv_path = str(tmp_path / "allocation.csv")
    try:
        with ShapedLink(name, rate="60mbit") as link, LinkRosGraph(link) as graph:
            available_mbps = link.measure_mbps(seconds=2)
            budget = (1 - RESERVE) * available_mbps / 8.0
            _start_load(graph, record_path)
            graph.start_python(
                "twin",
                find_node("cps_bw_manager", "bandwidth_manager"),
                [
                    "__name:=bandwidth_manager",
                    f"_available_mbps:={available_mbps:.3f}",
                    f"_reserve_fraction:={RESERVE}",
                    f"_csv_path:={csv_path}",
                ],
                name="manager",
            )
            _wait_for_file_rows(csv_path, 40.0)
            _wait_for_file_rows(record_path, 40.0)
            time.sleep(4.0)  # sizes measured and the first full allocation in force
            on_t0 = time.time()
            time.sleep(PHASE_S)
            on_t1 = time.time()

            manager = next(p for p in graph.sides["twin"].processes if p.cps_name == "manager")
            graph.sides["twin"].stop(manager)
            _set_all_rates(graph, 30.0)
            time.sleep(2.0)
            off_t0 = time.time()
            time.sleep(PHASE_S)
            off_t1 = time.time()
            manager_log = graph.output("manager")
    finally:
        netns_link.link_down(name)
    assert netns_link.list_namespaces() == [] or not any(ns.startswith(name) for ns in netns_link.list_namespaces())

    records = read_records(record_path)
    on, off = summarize(records, on_t0, on_t1), summarize(records, off_t0, off_t1)
    offered = sum(size * hz for size, hz in LOAD.values()) / 1e6
    print(
        f"\nlink: 60mbit tbf, iperf3 {available_mbps:.1f} Mbit/s -> budget {budget:.2f} MB/s "
        f"(4 % reserve); offered load {offered:.2f} MB/s ({8 * offered:.1f} Mbit/s)"
    )
    for label, s in (("manager on ", on), ("manager off", off)):
        print(
            f"{label}: consumed per 1 s window max {s.max_window_mbytes_per_s:.2f} MB/s, mean "
            f"{s.mean_mbytes_per_s:.2f} MB/s; latency p50 {s.latency_p50_ms:.0f} ms, p95 {s.latency_p95_ms:.0f} ms, "
            f"max {s.latency_max_ms:.0f} ms; rates " + ", ".join(f"{k} {v:.1f} Hz" for k, v in s.rates_hz.items())
        )
    assert on.messages > 0 and off.messages > 0, manager_log[-2000:]
    assert all(w <= budget for w in on.windows_mbytes_per_s), (on.windows_mbytes_per_s, budget)
    assert on.latency_p95_ms < 100.0, manager_log[-2000:]
    # Without the manager the offered load exceeds what the link can carry and queues build up.
    assert offered > available_mbps / 8.0
    assert off.latency_p95_ms > 2 * on.latency_p95_ms and off.latency_p95_ms > 100.0


def _delivered(stats_path):
    """(time, (delivered Mbit/s over the managed topics, worst latency avg ms)) from topic_stats' CSV."""
    by_time = {}
    with open(stats_path) as stream:
        for row in csv.DictReader(stream):
            t = float(row["time_s"])
            mbps, lat = by_time.get(t, (0.0, 0.0))
            latency = float(row["latency_avg_ms"]) if row["latency_avg_ms"] else 0.0
            by_time[t] = (mbps + 8 * float(row["bandwidth_mbytes_per_s"] or 0.0), max(lat, latency))
    return sorted(by_time.items())


def _estimates(csv_path):
    """(time, available Mbit/s) per manager update from its CSV log."""
    seen = {}
    with open(csv_path) as stream:
        for row in csv.DictReader(stream):
            seen[float(row["stamp_s"])] = float(row["available_mbps"])
    return sorted(seen.items())


@pytest.mark.skipif(_capable() is not None, reason=f"{_capable()}")
@pytest.mark.timeout(150)
# Traced, not fixed (issue 23): fed /tissue/stats' 2 s sliding averages, the delivery-rate estimator
# reads a draining queue's burst (29.6 Mbit/s "delivered" through a 20 Mbit/s shaper) as capacity
# and probes above 24 Mbit/s in 1 of 3 runs here; it needs the bridge's per-interval delivery
# reports. It is off by default (fleet.yaml estimate_bandwidth: false); the test still runs and its
# trace is printed, so an XPASS or XFAIL shows in every run.
@pytest.mark.xfail(strict=False, reason="issue 23: the estimator on 2 s averages probes above the link after a drop")
def test_estimate_tracks_the_link_going_60_20_60(tmp_path):
    """The manager estimates the capacity from /tissue/stats (cps_transport's topic_stats on the
    digital-twin side) while `cps_link set` changes the link 60 -> 20 -> 60 Mbit/s under load."""
    name = link_name("bwe")
    stats_path = str(tmp_path / "stats.csv")
    csv_path = str(tmp_path / "allocation.csv")
    marks = {}
    try:
        with ShapedLink(name, rate="60mbit") as link, LinkRosGraph(link) as graph:
            _start_load(graph)
            _start_topic_stats(graph, stats_path, window_s=2.0)
            graph.start_python(
                "twin",
                find_node("cps_bw_manager", "bandwidth_manager"),
                [
                    "__name:=bandwidth_manager",
                    "_available_mbps:=60.0",
                    "_estimate_bandwidth:=true",
                    f"_csv_path:={csv_path}",
                ],
                name="manager",
            )
            _wait_for_file_rows(csv_path, 40.0)
            _wait_for_file_rows(stats_path, 40.0)
            time.sleep(6.0)
            marks["drop"] = time.time()
            link.set_rate("20mbit")
            time.sleep(10.0)
            marks["rise"] = time.time()
            link.set_rate("60mbit")
            time.sleep(9.0)
            marks["end"] = time.time()
            manager_log = graph.output("manager")
    finally:
        netns_link.link_down(name)

    trace = _estimates(csv_path)
    delivered = _delivered(stats_path)
    print(
        "\nestimate of the available bandwidth while the link goes 60 -> 20 -> 60 Mbit/s "
        "(delivered: topic_stats at the digital twin, 2 s window):"
    )
    for t, mbps in trace:
        if marks["drop"] - 4 <= t <= marks["end"]:
            phase = "60" if t < marks["drop"] else "20" if t < marks["rise"] else "60"
            near = [v for ts, v in delivered if abs(ts - t) < 0.3]
            shown = f"{near[0][0]:5.1f} Mbit/s, latency {near[0][1]:5.0f} ms" if near else ""
            print(f"  t={t - marks['drop']:+6.1f} s link {phase} Mbit/s: estimate {mbps:5.1f}   delivered {shown}")

    def during(t0, t1):
        return [mbps for t, mbps in trace if t0 <= t < t1]

    low = during(marks["drop"] + 4.0, marks["rise"])
    high = during(marks["rise"], marks["rise"] + 8.0)
    assert low and high, manager_log[-2000:]
    # Within 4 s of the drop the estimate is at or below the new capacity (plus its probing margin)
    # and stays there; within 8 s of the recovery it is back near the full capacity.
    assert all(v <= 24.0 for v in low), low
    assert max(high) >= 45.0, high
