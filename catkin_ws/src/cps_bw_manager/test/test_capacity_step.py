"""A capacity drop 60 -> 5 Mbit/s applied by a cps_link scenario during a mission-like load: the
manager's online estimate follows it, and from 2 s after the drop every 1 s window of traffic
leaving the physical side stays within the measured 5 Mbit/s capacity less the reserve.

The windows are the bytes the physical side's shaping qdisc sent (everything that crossed the
link that way: clouds, TCP/IP headers, statuses), the capacity is iperf3's on the same link."""
import time

import pytest

from cps_fleet.csv_log import CsvLog
from cps_harness.processes import find_node
from cps_link import netns_link
from cps_link.link_run import LinkRosGraph
from cps_link.netns_link import ShapedLink
from cps_link.scenario import LINK_EVENTS_COLUMNS, ScenarioRunner, load_scenario
from test_over_link import (RESERVE, _capable, _estimates, _start_load, _start_topic_stats,
                            _wait_for_file_rows)

pytestmark = [pytest.mark.ros, pytest.mark.slow]
DROP_AT_S = 1.0
SETTLE_S = 2.0
OBSERVE_S = 12.0
BEFORE_S = 3.0


def _windows(samples, t0, t1):
    """Bytes per 1 s window [t0 + k, t0 + k + 1) from (time, cumulative bytes) samples, interpolated;
    only windows the samples cover."""
    t0, t1 = max(t0, samples[0][0]), min(t1, samples[-1][0])

    def at(t):
        before = max((s for s in samples if s[0] <= t), key=lambda s: s[0])
        after = min((s for s in samples if s[0] >= t), key=lambda s: s[0])
        if after[0] == before[0]:
            return before[1]
        return before[1] + (after[1] - before[1]) * (t - before[0]) / (after[0] - before[0])
    return [at(t0 + k + 1) - at(t0 + k) for k in range(int(t1 - t0))]


@pytest.mark.skipif(_capable() is not None, reason=f"{_capable()}")
@pytest.mark.timeout(180)
def test_every_window_fits_the_measured_capacity_2_s_after_a_drop_to_5mbit(tmp_path):
    name = "cpskstep"
    scenario_file = tmp_path / "drop.yaml"
    scenario_file.write_text(f"initial: {{rate_mbps: 60}}\nsteps:\n  - {{at_s: {DROP_AT_S}, rate_mbps: 5}}\n")
    scenario = load_scenario(str(scenario_file))
    stats_path, csv_path = str(tmp_path / "stats.csv"), str(tmp_path / "allocation.csv")
    samples = []
    try:
        with ShapedLink(name, rate="5mbit") as link:
            capacity_low = link.measure_mbps(seconds=2)
            link.set_rate("60mbit")
            capacity_high = link.measure_mbps(seconds=2)
            with LinkRosGraph(link) as graph:
                _start_load(graph)
                _start_topic_stats(graph, stats_path, window_s=1.0)
                graph.start_python("twin", find_node("cps_bw_manager", "bandwidth_manager"),
                                   ["__name:=bandwidth_manager", f"_available_mbps:={capacity_high:.3f}",
                                    f"_reserve_fraction:={RESERVE}", "_estimate_bandwidth:=true",
                                    # one decrease per statistics publication (2 Hz of 1 s windows)
                                    "_estimate_holdoff_s:=0.5",
                                    f"_csv_path:={csv_path}"], name="manager")
                _wait_for_file_rows(csv_path, 40.0)
                _wait_for_file_rows(stats_path, 40.0)
                time.sleep(6.0)
                with CsvLog(str(tmp_path / "link_events.csv"), LINK_EVENTS_COLUMNS) as events:
                    runner = ScenarioRunner(name, scenario, events, log=print)
                    start = time.monotonic() + BEFORE_S
                    while time.monotonic() < start + DROP_AT_S + SETTLE_S + OBSERVE_S + 0.5:
                        if not runner.applied and time.monotonic() >= start:
                            runner.start(start)
                        samples.append((time.monotonic(), link.qdisc_bytes_sent("phys")))
                        time.sleep(0.1)
                    runner.stop()
                manager_log = graph.output("manager")
    finally:
        netns_link.link_down(name)
    assert not [ns for ns in netns_link.list_namespaces() if ns.startswith(f"{name}_")]

    assert [(kind, s.rate_mbps) for _, kind, s, note in runner.applied] == [("start", 60.0), ("shape", 5.0)]
    assert not runner.errors
    drop = start + runner.applied[1][0]
    limit_bytes = (1 - RESERVE) * capacity_low * 1e6 / 8
    before = _windows(samples, start - BEFORE_S, drop)
    after = _windows(samples, drop, drop + SETTLE_S + OBSERVE_S)
    print(f"\niperf3: {capacity_high:.1f} Mbit/s at 60mbit, {capacity_low:.2f} Mbit/s at 5mbit -> limit "
          f"{8 * limit_bytes / 1e6:.2f} Mbit/s per 1 s window after the drop")
    print("sent by the physical side per 1 s window, Mbit/s: before " + " ".join(f"{8 * b / 1e6:.1f}" for b in before)
          + " | after the drop " + " ".join(f"{8 * b / 1e6:.2f}" for b in after))
    trace = _estimates(csv_path)
    print("manager's estimate after the drop, Mbit/s: " + " ".join(
        f"{t - (time.time() - time.monotonic() + drop):+.1f}:{v:.1f}" for t, v in trace
        if drop - 2 <= t - (time.time() - time.monotonic()) <= drop + SETTLE_S + OBSERVE_S))
    late = after[int(SETTLE_S):]
    assert late, manager_log[-2000:]
    assert all(b <= limit_bytes for b in late), ([8 * b / 1e6 for b in late], 8 * limit_bytes / 1e6,
                                                 manager_log[-3000:])
    # The load really needed the manager: before the drop it sent far above the new capacity.
    assert max(before) > 3 * limit_bytes
