"""Run the twins across cps_link's shaped link: the supervisor joins the digital-twin
namespace (where roscore and the digital side run) and starts the physical side in the other.

Entering a network namespace with setns(2) changes only the calling thread; the supervisor calls
it from its main thread before it starts rospy or any process, so everything it starts afterwards
is on the digital-twin host, and it returns to its own namespace before the link is removed.
"""

import concurrent.futures
import contextlib
import ctypes
import dataclasses
import os
import re

from cps_link.netns_link import (
    PHYS_IP,
    TWIN_IP,
    LinkError,
    ShapedLink,
    check_capability,
    link_down,
    link_exists,
    list_namespaces,
    namespace,
)
from cps_ros.processes import process_running

RUN_LINK_PREFIX = "cps"
_RUN_NAMESPACE = re.compile(rf"^{RUN_LINK_PREFIX}(\d+)_[a-z]+$")
_CLONE_NEWNET = 0x40000000


def run_link_name(pid=None):
    """The link of one bringup run, `cps<pid>` (at most 10 characters for any pid_max): two runs
    on one machine, or a run beside a killed one's leftovers, never meet on a fixed name."""
    return f"{RUN_LINK_PREFIX}{os.getpid() if pid is None else pid}"


def remove_stale_run_links(log=print):
    """Remove the links of earlier runs (`cps<pid>`) whose bringup died without removing them
    (SIGKILL): their pid is gone or a zombie. Returns the names removed."""
    stale = set()
    for ns in list_namespaces():
        match = _RUN_NAMESPACE.match(ns)
        if match and not process_running(int(match.group(1))):
            stale.add(f"{RUN_LINK_PREFIX}{match.group(1)}")
    for name in sorted(stale):
        link_down(name)
        log(f"[bringup] removed link {name}, left by a run that is gone")
    return sorted(stale)


def link_unavailable_reason():
    """None when this process can create the link, else why not (not root, no netns, no tc)."""
    try:
        check_capability()
    except LinkError as exc:
        return str(exc)
    return None


def _setns(fd):
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    if libc.setns(fd, _CLONE_NEWNET) != 0:
        errno = ctypes.get_errno()
        raise LinkError(f"setns failed: {os.strerror(errno)}")


@dataclasses.dataclass
class NamespacedLink:
    name: str
    rate: str
    measured_mbps: float
    scenario: object = None  # a cps_link.scenario.Scenario to run during the mission, or None
    phys_ip: str = PHYS_IP
    twin_ip: str = TWIN_IP
    guarded_ports: tuple = ()  # set by guard(): ((host, its listening ports), ...)

    def exec_prefix(self, side):
        return ["ip", "netns", "exec", namespace(self.name, side)]

    def netns_path(self, side):
        return f"/var/run/netns/{namespace(self.name, side)}"

    def start_scenario(self, csv_path, log=print, on_rate=None):
        """Start the scenario's runner (mission time 0 is now); returns it, or None without one.
        `on_rate(mission_s, rate_mbps)`: told the rate at start and at each applied rate step."""
        if self.scenario is None:
            return None
        from cps_fleet.csv_log import CsvLog
        from cps_link.scenario import LINK_EVENTS_COLUMNS, ScenarioRunner

        runner = ScenarioRunner(
            self.name, self.scenario, CsvLog(csv_path, LINK_EVENTS_COLUMNS), log=log, on_rate=on_rate
        )
        runner.start()
        return runner

    def guard(self, listen_ports):
        """From now on each host answers only at its own bridge listener (netns_link.guard_hosts;
        `listen_ports`: "phys" or "twin" -> ports): the twin's main lane, the robots' command lane."""
        from cps_link.netns_link import guard_hosts

        guard_hosts(self.name, listen_ports)
        self.guarded_ports = tuple((host, tuple(sorted(ports))) for host, ports in sorted(listen_ports.items()))

    def describe(self):
        return (
            ("shared-medium " if self.scenario and self.scenario.topology == "shared" else "")
            + f"tc-shaped {self.rate} veth between namespaces {namespace(self.name, 'phys')} ({self.phys_ip}) and "
            f"{namespace(self.name, 'twin')} ({self.twin_ip}); iperf3 measured {self.measured_mbps:.1f} Mbit/s"
            + (f"; scenario {self.scenario.name}" if self.scenario else "")
            + (
                "; each host answers only at its link listener: "
                + ", ".join(f"{host} {list(ports)}" for host, ports in self.guarded_ports)
                if self.guarded_ports
                else ""
            )
        )


class CapacityAnnouncer:
    """Publishes the link's capacity as tc sets it (cps_msgs/LinkCapacity, latched) on this
    process's master, the twin's, where the bandwidth manager runs: always on
    names.LINK_TRUE_CAPACITY, the test bed's oracle that the GUI and the reports set the manager's
    estimate against; with `to_manager` also on names.LINK_CAPACITY, what a link that knows its rate
    (a modem, a Wi-Fi driver) would announce and the manager allocates from. rospy must be up."""

    def __init__(self, link, log=print, to_manager=True):

        from cps_fleet import names
        from cps_msgs.msg import LinkCapacity
        from cps_ros.publisher import Publisher

        self.link, self.log, self.to_manager = link, log, to_manager
        self.source = f"tc scenario {link.scenario.name}" if link.scenario else f"tc link {link.rate}"
        self.announced = []  # (mission s, Mbit/s)
        self._msg = LinkCapacity
        self._oracle = Publisher(names.LINK_TRUE_CAPACITY, LinkCapacity, queue_size=10, latch=True)
        self._pub = Publisher(names.LINK_CAPACITY, LinkCapacity, queue_size=10, latch=True) if to_manager else None

    def on_rate(self, mission_s, rate_mbps):
        import rospy

        msg = self._msg(capacity_mbps=float(rate_mbps), source=self.source)
        msg.header.stamp = rospy.Time.now()
        self._oracle.publish(msg)
        if self._pub is None:
            return
        self._pub.publish(msg)
        self.announced.append((mission_s, float(rate_mbps)))
        self.log(f"[link] {mission_s:6.1f} s: announced {rate_mbps:g} Mbit/s on {self._pub.resolved_name}")

    def announce_fixed_rate(self):
        """A link without a scenario: its tc rate, once, at the start."""
        from cps_link.netns_link import rate_bits_per_s

        self.on_rate(0.0, rate_bits_per_s(self.link.rate) / 1e6)

    def describe(self):
        if self._pub is None:
            return f"not announced to the manager ({self.source} only on {self._oracle.resolved_name}, the oracle)"
        if not self.announced:
            return f"announce asked, nothing announced ({self.source})"
        steps = ", ".join(f"{mbps:g} Mbit/s at {t:.0f} s" for t, mbps in self.announced)
        return f"announced on {self._pub.resolved_name} by {self.source}: {steps}"


class InNamespace:
    """A RosGraph whose every call runs in another network namespace: one worker thread enters it
    with setns(2) (only that thread moves), and the processes it starts are forked there."""

    def __init__(self, graph, netns_path):
        self.graph = graph
        self._pool = concurrent.futures.ThreadPoolExecutor(1, initializer=self._enter, initargs=(netns_path,))

    @staticmethod
    def _enter(path):
        fd = os.open(path, os.O_RDONLY)
        try:
            _setns(fd)
        finally:
            os.close(fd)

    def __getattr__(self, name):
        attr = getattr(self.graph, name)
        if not callable(attr):
            return attr
        return lambda *args, **kwargs: self._pool.submit(attr, *args, **kwargs).result()

    def close(self):
        try:
            self._pool.submit(self.graph.close).result()
        finally:
            self._pool.shutdown()


@contextlib.contextmanager
def namespaced_link(rate, log=print, scenario=None, name=None):
    """Create the link (with `scenario`: its topology and initial rate; `name` None: this run's
    own, after removing dead runs' links), measure it, move this thread into the twin namespace;
    undo all on exit."""
    check_capability()
    if name is None:
        remove_stale_run_links(log)
        name = run_link_name()
    if link_exists(name):
        raise LinkError(
            f"a link named {name} already exists (another run?); remove it with `cps_link down --name {name}`"
        )
    shaping = {}
    if scenario is not None:
        from cps_link.netns_link import netem_available, tc_rate

        rate = tc_rate(scenario.initial.rate_mbps)
        shaping = dict(topology=scenario.topology, with_netem=netem_available())
    with ShapedLink(name=name, rate=rate, **shaping) as link:
        measured = link.measure_mbps(seconds=2.0)
        log(f"[bringup] link {rate}: iperf3 measured {measured:.1f} Mbit/s physical → digital twin")
        home = os.open("/proc/self/ns/net", os.O_RDONLY)
        target = os.open(f"/var/run/netns/{namespace(name, 'twin')}", os.O_RDONLY)
        try:
            _setns(target)
            try:
                yield NamespacedLink(name, rate, measured, scenario)
            finally:
                _setns(home)
        finally:
            os.close(target)
            os.close(home)
