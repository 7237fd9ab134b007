"""Over the real shaped link (60 Mbit/s tbf between two namespaces): four robots publish realistic
compressed clouds (Table 6 sizes) through cps_transport's rate limiters. Over TCPROS across the
link, manager on: every 1 s window of consumed bandwidth stays within the budget and latency p95 <
100 ms (the paper's bound); manager off: the same load overruns the link and latency grows. Over
the Zenoh bridges: the manager's online estimate follows the link 60 -> 20 -> 60 Mbit/s."""

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
ESTIMATE_BAND, ESTIMATE_SETTLE_S = 0.15, 2.0  # issue 35: within +-15 % of the true capacity 2 s after a step


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


def _start_limiters(graph, record_path=None):
    """cps_transport's rate limiters on the physical side, the recorder on the twin.

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


def _start_cloud_load(graph):
    """The Table 6 cloud load into the limiters (physical side only: it does not cross the link)."""
    graph.start_python(
        "phys",
        find_node("cps_harness", "cloud_load"),
        [f"{r}:{size}:{hz}" for r, (size, hz) in LOAD.items()],
        name="load",
    )


def _cloud_rows(csv_path):
    """(stamp s, robot, rate in force Hz, measured message bytes) of the manager's cloud rows."""
    with open(csv_path) as stream:
        return [
            (float(row["stamp_s"]), row["robot"], float(row["rate_hz"]), float(row["message_bytes"]))
            for row in csv.DictReader(stream)
            if row["stream"] == "cloud"
        ]


def _wait_for_measured_sizes(csv_path, timeout_s):
    """Until the manager's allocation uses every robot's measured cloud size (within 10 % of LOAD's)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        latest = {robot: size for _, robot, _, size in _cloud_rows(csv_path)}
        if all(abs(latest.get(r, 0.0) / size - 1.0) <= 0.1 for r, (size, _) in LOAD.items()):
            return
        time.sleep(0.2)
    raise AssertionError(f"the manager did not measure every cloud's size within {timeout_s} s: {latest}")


def _rate_changes(csv_path):
    """The manager's cloud rows where a robot's rate or size in force changed (a failure's timeline)."""
    last, changes = {}, []
    for stamp, robot, rate, size in _cloud_rows(csv_path):
        if last.get(robot) != (rate, size):
            last[robot] = (rate, size)
            changes.append(f"{stamp:.2f} {robot} {rate:.2f} Hz {size:.0f} B")
    return "\n".join(changes)


def _assert_each_side_in_its_group(graph):
    """Every process started on a side runs in that side's cgroup (link_run.side_hosts): the side
    weighs as a host against a mission on the other test worker."""
    from cps_harness.cgroups import groups_of
    from cps_harness.link_run import LINK_SIDES

    if graph.hosts.mode != "cgroup":
        return
    for side, side_graph in graph.sides.items():
        for process in side_graph.processes:
            groups = groups_of(process.pid)
            assert groups is None or groups.get("cpu") == f"/{graph.hosts.name}/{LINK_SIDES[side]}", (
                process.cps_name,
                groups,
            )


def _latency_timeline(records, t0, t1, step_s=0.5):
    """Per `step_s` of [t0, t1) by receive time: each robot's messages and worst latency, so that a
    failure says when latency grew and whose (CI on 1d27b42: p95 270 ms, max 773 ms, untraced)."""
    lines = []
    for k in range(int((t1 - t0) / step_s)):
        a = t0 + k * step_s
        inside = [r for r in records if a <= r.receive_s < a + step_s]
        per_robot = {}
        for r in inside:
            n, worst = per_robot.get(r.robot, (0, 0.0))
            per_robot[r.robot] = (n + 1, max(worst, r.latency_ms))
        lines.append(
            f"{a - t0:4.1f} s: "
            + ", ".join(f"{robot} {n} max {worst:.0f} ms" for robot, (n, worst) in sorted(per_robot.items()))
        )
    return "\n".join(lines)


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
            # As deployed: the manager is connected to the limiters before the load fills the link;
            # the phase begins once it allocates from every measured size.
            _start_limiters(graph, record_path)
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
            _start_cloud_load(graph)
            _wait_for_file_rows(record_path, 40.0)
            _wait_for_measured_sizes(csv_path, 40.0)
            _assert_each_side_in_its_group(graph)
            time.sleep(4.0)  # the allocation from the measured sizes in force at the limiters
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
    assert all(w <= budget for w in on.windows_mbytes_per_s), (
        on.windows_mbytes_per_s,
        budget,
        f"phase {on_t0:.2f}-{on_t1:.2f}",
        _rate_changes(csv_path),
    )
    assert on.latency_p95_ms < 100.0, (
        manager_log[-2000:],
        _latency_timeline(records, on_t0, on_t1),
        _rate_changes(csv_path),
    )
    # Without the manager the offered load exceeds what the link can carry and queues build up.
    assert offered > available_mbps / 8.0
    assert off.latency_p95_ms > 2 * on.latency_p95_ms and off.latency_p95_ms > 100.0


def _estimates(csv_path):
    """(time, capacity Mbit/s, allocation target Mbit/s, delivered Mbit/s, sent Mbit/s, mode, why) per
    link report from the manager's link_estimate.csv; `why`: what the estimator had to go on (the
    sender app-limited or not, an overuse, a train's reading), printed so that a failure's trace
    says it (pkg-alone 2026-11-30: a rise missed for 8 s, its CSV gone before it was read)."""
    rows = []
    with open(csv_path) as stream:
        for row in csv.DictReader(stream):
            train = row.get("probe_train_mbps", "")
            why = f"app-limited {row.get('app_limited', '')}; socket full {row.get('sender_socket_full', '')}" + (
                f"; overuse {row['overuse']}" if row.get("overuse") else ""
            )
            if row.get("refused"):
                why += f"; REFUSED {row['refused']}"
            if row.get("probe_refused"):
                why += f"; trains refused {row['probe_refused']}"
            if train:
                why += (
                    f"; train {float(train):.1f} sent at {float(row['probe_train_sent_mbps'] or 'nan'):.1f}, "
                    f"receiver waited {row.get('probe_train_receiver_wait_ms', '')} ms"
                )
            rows.append(
                (
                    float(row["stamp_s"]),
                    float(row["capacity_mbps"]),
                    float(row["estimate_mbps"]),
                    float(row["delivered_mbps"] or "nan"),
                    float(row["sent_mbps"] or "nan"),
                    row["mode"],
                    why,
                )
            )
    return rows


@pytest.mark.skipif(_capable() is not None, reason=f"{_capable()}")
@pytest.mark.timeout(180)
def test_estimate_tracks_the_link_going_60_20_60(tmp_path):
    """The manager estimates the capacity from the Zenoh bridges' link reports (per 0.5 s interval:
    delivered at the twin, sent by the robots' bridge, app-limited, heartbeat round trips) while
    `cps_link set` changes the link 60 -> 20 -> 60 Mbit/s under a load above it. Issue 23's xfail
    fed it /tissue/stats' 2 s sliding averages over TCPROS; a draining queue's burst read as
    capacity (29.6 Mbit/s "delivered" through 20) and it probed above 24 Mbit/s in 1 of 3 runs."""
    from cps_harness.transport_compare import Graphs, start_estimating_manager, start_limited_load
    from cps_link.zenoh_session import bridge_node_name, default_cert_dir, ensure_certs

    name = link_name("bwe")
    csv_path = str(tmp_path / "link_estimate.csv")
    marks = {}
    try:
        with ShapedLink(name, rate="60mbit") as link:
            graphs = Graphs(link, "zenoh", ensure_certs(default_cert_dir()))
            try:
                start_limited_load(graphs, LOAD)
                start_estimating_manager(graphs, list(LOAD), 60.0, csv_path)
                _wait_for_file_rows(csv_path, 40.0)
                time.sleep(6.0)
                marks["drop"] = time.time()
                link.set_rate("20mbit")
                time.sleep(10.0)
                marks["rise"] = time.time()
                link.set_rate("60mbit")
                time.sleep(9.0)
                marks["end"] = time.time()
                manager_log = graphs.output("manager")
                bridge_log = "\n".join(
                    graphs.output(bridge_node_name(role, lane))
                    for role in ("twin", "robots")
                    for lane in ("main", "command")
                )
            finally:
                graphs.close()
    finally:
        netns_link.link_down(name)

    trace = _estimates(csv_path)
    print("\nestimate of the link while it goes 60 -> 20 -> 60 Mbit/s (the bridges' link reports):")
    for t, capacity, target, delivered, sent, mode, why in trace:
        if marks["drop"] - 4 <= t <= marks["end"]:
            phase = "60" if t < marks["drop"] else "20" if t < marks["rise"] else "60"
            print(
                f"  t={t - marks['drop']:+6.1f} s link {phase}: capacity {capacity:5.1f} target {target:5.1f} ({mode}); "
                f"delivered {delivered:5.1f} sent {sent:5.1f} Mbit/s; {why}"
            )
    # the link's state as the manager saw it: an outage declared after a step pauses the allocation
    # and restarts the estimator's per-interval state (a report from before it is refused)
    link_lines = [line for line in manager_log.splitlines() if "bandwidth manager: link" in line]
    print("the manager's link state changes:", *(link_lines or ["none"]), sep="\n  ")
    bridge_lines = [line for line in bridge_log.splitlines() if ": link " in line]
    print("the bridges' link state changes (and why):", *(bridge_lines or ["none"]), sep="\n  ")

    def during(t0, t1):
        return [(capacity, target, mode) for t, capacity, target, _, _, mode, _ in trace if t0 <= t < t1]

    low = during(marks["drop"] + ESTIMATE_SETTLE_S, marks["rise"])
    high = during(marks["rise"], marks["rise"] + 8.0)
    assert low and high, manager_log[-2000:]
    # The bar: from 2 s after the drop the estimate of the link (capacity_mbps) is within
    # +-15 % of 20 Mbit/s and stays there. Out of a probe the manager allocates no more than that
    # (estimate_mbps); a probe allocates above it on purpose, for at most probe_max_s (its target is
    # gain x the capacity plus the fleet's unfilled gap: estimation.PROBE_GAP_FRACTION).
    assert all(abs(capacity / 20.0 - 1.0) <= ESTIMATE_BAND for capacity, _, _ in low), low
    assert all(target <= 20.0 * (1.0 + ESTIMATE_BAND) for _, target, mode in low if mode != "probe"), low
    # Within 8 s of the recovery the estimate is back near the full capacity.
    assert max(capacity for capacity, _, _ in high) >= 45.0, high
