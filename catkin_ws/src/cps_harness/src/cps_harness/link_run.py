"""ROS across the shaped link: a master in the digital-twin namespace, processes on either side,
and the analysis of what crossed (bandwidth per 1 s window, latency percentiles).

    with ShapedLink("cpsbw") as link, LinkRosGraph(link) as graph:
        graph.start("phys", [python, node, ...], name="limiter")
"""

import dataclasses
import math
import os
import subprocess
import sys
import time
from typing import List

import numpy as np

from cps_bringup.plan import DIGITAL, PHYSICAL
from cps_fleet import names
from cps_link.netns_link import PHYS_IP, TWIN_IP, ClosingContext
from cps_ros.processes import RosGraph, free_port

# The link tests' sides as the host split names them, and the prefix of their cgroups' names.
LINK_SIDES = {"phys": PHYSICAL, "twin": DIGITAL}
SIDE_GROUP = "cpslinktest"


def side_hosts(name, cpus=None):
    """Each side of a link test as a host, as a mission's sides are (cps_bringup.host_split): a
    cgroup per side with a mission side's cpu.shares, on `cpus` ({"phys"|"twin": CPU list}; every
    CPU by default). A HostSplit: enter it, start each side's processes behind `prefix(side)`.

    Without it the test's processes weighed 1024 each against a mission's or a replay's 8192-16384
    a side on the same two CPUs (make test runs them side by side). In CI on 1d27b42
    test_over_link's manager-on latency reached p95 270 ms, max 773 ms (alone: p95 31-42 ms); beside
    two busy loops at a replay's 16384 shares its p95 was 49 ms, 34-37 ms with these groups."""
    from cps_bringup.host_split import MISSION_SIDE_SHARES, HostSplit, online_cpus

    every = online_cpus()
    per_side = {
        LINK_SIDES[side]: tuple(int(c) for c in str((cpus or {}).get(side) or "").split(",") if c) or every
        for side in LINK_SIDES
    }
    return HostSplit.choose(per_side, name=f"{name}_{os.getpid()}", shares=dict.fromkeys(per_side, MISSION_SIDE_SHARES))


class LinkRosGraph(ClosingContext):
    """A roscore in the twin namespace and every process started on either side, each side in its
    own cgroup (`side_hosts`); `close` kills all and removes the groups."""

    def __init__(self, link, port=None, cpus=None):
        self.link = link
        self.port = port or free_port()
        self.uri = f"http://{TWIN_IP}:{self.port}"
        self.sides = {
            "twin": RosGraph(master_uri=self.uri, host_ip=TWIN_IP),
            "phys": RosGraph(master_uri=self.uri, host_ip=PHYS_IP),
        }
        self.hosts = side_hosts(SIDE_GROUP, cpus)
        self._hosts_entered = False

    def __enter__(self):
        return self._set_up_or_close(self._start_master)

    def _start_master(self):
        self.hosts.__enter__()
        self._hosts_entered = True
        self.start("twin", ["roscore", "-p", str(self.port)], name="roscore")
        self.wait_for_master()

    def start(self, side, argv, name):
        # into the side's cgroup before `ip netns exec`, which mounts a /sys without the cgroups
        argv = self.hosts.prefix(LINK_SIDES[side]) + self.link.argv(side, argv, master_port=self.port)
        return self.sides[side].popen(argv, name=name)

    def start_python(self, side, path, args=(), name=None):
        return self.start(side, [sys.executable, path, *args], name=name or path.rsplit("/", 1)[-1])

    def run_python(self, side, code, timeout_s=30.0):
        """Run a short python snippet on one side against the master; returns CompletedProcess."""
        return subprocess.run(
            self.link.argv(side, [sys.executable, "-c", code], master_port=self.port),
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )

    def wait_for_master(self, timeout_s=30.0):
        code = (
            "import rosgraph,sys; sys.exit(0 if rosgraph.Master('cps_probe').is_online() "
            f"and '{names.ROSOUT}' in str(rosgraph.Master('cps_probe').getSystemState()) else 1)"
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.run_python("twin", code).returncode == 0:
                defaults = f"from cps_ros.processes import set_master_defaults; set_master_defaults({self.uri!r})"
                done = self.run_python("twin", defaults)
                if done.returncode != 0:
                    raise RuntimeError(f"could not set the master's defaults: {done.stderr[-2000:]}")
                return
            time.sleep(0.2)
        raise TimeoutError(f"no ROS master at {self.uri} within {timeout_s} s:\n{self.output('roscore')[-2000:]}")

    def output(self, name):
        return "\n".join(graph.output(name) for graph in self.sides.values())

    def close(self):
        try:
            for side in ("phys", "twin"):
                self.sides[side].close()
        finally:
            if self._hosts_entered:
                self._hosts_entered = False
                self.hosts.__exit__(None, None, None)


@dataclasses.dataclass(frozen=True)
class Record:
    robot: str
    receive_s: float
    stamp_s: float
    size_bytes: int

    @property
    def latency_ms(self):
        return 1000.0 * (self.receive_s - self.stamp_s)


def read_records(path) -> List[Record]:
    """The link recorder's lines `robot receive_s stamp_s bytes`; a torn last line is skipped."""
    records = []
    with open(path) as stream:
        for line in stream:
            parts = line.split()
            if len(parts) == 4:
                records.append(Record(parts[0], float(parts[1]), float(parts[2]), int(parts[3])))
    return records


@dataclasses.dataclass(frozen=True)
class PhaseSummary:
    windows_mbytes_per_s: List[float]
    latency_p50_ms: float
    latency_p95_ms: float
    latency_max_ms: float
    messages: int
    rates_hz: dict

    @property
    def max_window_mbytes_per_s(self):
        return max(self.windows_mbytes_per_s) if self.windows_mbytes_per_s else math.nan

    @property
    def mean_mbytes_per_s(self):
        return float(np.mean(self.windows_mbytes_per_s)) if self.windows_mbytes_per_s else math.nan


def summarize(records, t0, t1, window_s=1.0) -> PhaseSummary:
    """Consumed MB/s in every `window_s` window of [t0, t1) (by receive time) and the latencies."""
    inside = [r for r in records if t0 <= r.receive_s < t1]
    n_windows = int((t1 - t0) // window_s)
    sums = np.zeros(n_windows)
    for r in inside:
        k = int((r.receive_s - t0) // window_s)
        if k < n_windows:
            sums[k] += r.size_bytes
    latencies = np.array([r.latency_ms for r in inside]) if inside else np.array([math.nan])
    duration = n_windows * window_s
    rates = {}
    for r in inside:
        rates[r.robot] = rates.get(r.robot, 0) + 1
    return PhaseSummary(
        windows_mbytes_per_s=list(sums / window_s / 1e6),
        latency_p50_ms=float(np.percentile(latencies, 50)),
        latency_p95_ms=float(np.percentile(latencies, 95)),
        latency_max_ms=float(np.max(latencies)),
        messages=len(inside),
        rates_hz={k: v / duration for k, v in sorted(rates.items())} if duration else {},
    )
