"""The idle share of the CPUs this process may run on, from /proc/stat (no ROS).

An encoder reports it in its status (cps_msgs/RateLimiterStatus `host`, `host_cpus`,
`host_idle_fraction`) so that the bandwidth manager buys finer detail only where the CPU to
produce it exists (issue 36). The CPUs are the process's affinity (a host split's cpuset); the
host is named by the computer and those CPUs, so every encoder on the same CPUs names the same
host. Idle counts `idle` and `iowait` jiffies. One meter per process (`shared()`): each caller
gets the share over the last whole `min_interval_s` or more, so many limiters in one process
neither shorten each other's interval nor read /proc/stat more than once a second.
"""

import math
import os
import socket
import threading
import time

MIN_INTERVAL_S = 1.0


def cpu_list_text(cpus):
    """0,1,2,5 -> '0-2,5'."""
    cpus = sorted(cpus)
    parts, start = [], None
    for k, cpu in enumerate(cpus):
        if start is None:
            start = cpu
        if k + 1 == len(cpus) or cpus[k + 1] != cpu + 1:
            parts.append(str(start) if start == cpu else f"{start}-{cpu}")
            start = None
    return ",".join(parts)


def read_cpu_jiffies(cpus, stat_path="/proc/stat"):
    """(idle, total) jiffies summed over `cpus` (ValueError if a CPU is missing or a line is bad)."""
    idle = total = 0
    seen = set()
    with open(stat_path) as stream:
        for line in stream:
            name, _, rest = line.partition(" ")
            if not name.startswith("cpu") or name == "cpu":
                continue
            cpu = int(name[3:])
            if cpu not in cpus:
                continue
            fields = [int(x) for x in rest.split()]
            if len(fields) < 5:
                raise ValueError(f"{stat_path}: {name} has {len(fields)} fields")
            idle += fields[3] + fields[4]
            total += sum(fields[:8])  # user nice system idle iowait irq softirq steal (guest is in user)
            seen.add(cpu)
    missing = set(cpus) - seen
    if missing:
        raise ValueError(f"{stat_path}: no line for cpu {cpu_list_text(missing)}")
    return idle, total


class HostCpu:
    def __init__(self, cpus=None, stat_path="/proc/stat", clock=time.monotonic, min_interval_s=MIN_INTERVAL_S):
        self.cpus = frozenset(os.sched_getaffinity(0) if cpus is None else cpus)
        self.stat_path = stat_path
        self.clock = clock
        self.min_interval_s = min_interval_s
        self.host = f"{socket.gethostname()} cpus {cpu_list_text(self.cpus)}"
        self._lock = threading.Lock()
        self._last = None  # (time, idle, total)
        self._idle_fraction = math.nan
        self.errors = 0

    @property
    def cores(self):
        return float(len(self.cpus))

    def idle_fraction(self):
        """The idle share of the host's CPUs over the last interval of at least min_interval_s
        (NaN before the second reading, or if /proc/stat cannot be read: counted in `errors`)."""
        with self._lock:
            now = self.clock()
            if self._last is not None and now - self._last[0] < self.min_interval_s:
                return self._idle_fraction
            try:
                idle, total = read_cpu_jiffies(self.cpus, self.stat_path)
            except (OSError, ValueError):
                self.errors += 1
                return math.nan
            if self._last is not None and total > self._last[2]:
                self._idle_fraction = min(1.0, max(0.0, (idle - self._last[1]) / (total - self._last[2])))
            self._last = (now, idle, total)
            return self._idle_fraction


_SHARED = None
_SHARED_LOCK = threading.Lock()


def shared() -> HostCpu:
    """The process's one meter."""
    global _SHARED
    with _SHARED_LOCK:
        if _SHARED is None:
            _SHARED = HostCpu()
        return _SHARED
