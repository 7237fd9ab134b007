"""The same load over either transport, on a shaped link (the link benchmark and its tests): one
master across the link (tcpros, the paper's set-up) or a master per side joined by the Zenoh
bridges. Processes on either side, the cloud load, teleop latency and the bridges' CPU."""

import contextlib
import sys
import time

import numpy as np

from cps_fleet import names
from cps_harness.link_run import LINK_SIDES, SIDE_GROUP, LinkRosGraph, side_hosts
from cps_link.netns_link import PHYS_IP, TWIN_IP, namespace
from cps_link.zenoh_session import bridge_argv, bridge_node_name
from cps_ros.processes import RosGraph, find_node, process_cpu_s

CLOUD_LOAD = find_node("cps_harness", "cloud_load")
TELEOP_PROBE = find_node("cps_harness", "teleop_probe")
# Within the budget of a 60 Mbit/s link (~4.9 MB/s of ~7.2): Table 6's sizes at managed rates.
LIVE = {"scout": (34000, 10.0), "jackal": (142000, 10.0), "champ": (60000, 20.0), "iris": (67000, 20.0)}
# Saturating: ~17 MB/s offered.
SATURATING = {"scout": (34000, 10.0), "jackal": (142000, 30.0), "champ": (60000, 30.0), "iris": (67000, 30.0)}


class Graphs:
    """Processes on either side: one master across the link (tcpros) or one per side (zenoh), each
    side's in its own cgroup with a host's weight (cps_harness.link_run.side_hosts). `cpus`:
    {side: CPU list} pins each side's processes (bridges included), as bringup's host split does;
    None: every CPU."""

    def __init__(self, link, transport, cert_dir, cpus=None):
        self.link, self.transport = link, transport
        self.stack = contextlib.ExitStack()
        if transport == "tcpros":
            self.tcpros = self.stack.enter_context(LinkRosGraph(link, cpus=cpus))
        else:
            self.hosts = self.stack.enter_context(side_hosts(SIDE_GROUP, cpus))
            self.sides = {}
            from cps_bringup.link import InNamespace

            for side in ("phys", "twin"):
                graph = InNamespace(RosGraph(host_ip="127.0.0.1"), f"/var/run/netns/{namespace(link.name, side)}")
                self.stack.callback(graph.close)
                graph.start()
                self.sides[side] = graph
            robots = list(LIVE)
            # each side's two lanes, as the bringup starts them: commands in their own connection,
            # marked for the link's voice queue (bridge.yaml command_dscp); named as the bringup names them
            self.bridges = []
            for lane in ("main", "command"):
                for side, role in (("twin", "twin"), ("phys", "robots")):
                    argv = bridge_argv(
                        sys.executable, role, TWIN_IP, robots, cert_dir, lane=lane, robots_address=PHYS_IP
                    )
                    self.bridges.append(self.start(side, argv, bridge_node_name(role, lane)))

    def start(self, side, argv, name):
        if self.transport == "tcpros":
            return self.tcpros.start(side, argv, name)
        return self.sides[side].popen(self.hosts.prefix(LINK_SIDES[side]) + list(argv), name=name)

    def output(self, name):
        if self.transport == "tcpros":
            return self.tcpros.output(name)
        return "\n".join(graph.output(name) for graph in self.sides.values())

    def stop(self, side, proc):
        graph = self.tcpros.sides[side] if self.transport == "tcpros" else self.sides[side]
        graph.stop(proc, timeout_s=3.0)

    def managed_topic_on_twin(self, robot):
        managed = names.managed_cloud(robot) if self.transport == "tcpros" else names.managed_cloud_at_twin(robot)
        return names.absolute(managed)

    def close(self):
        self.stack.close()


def start_load(graphs, streams, name):
    return graphs.start(
        "phys",
        [
            sys.executable,
            CLOUD_LOAD,
            *[f"{r}:{s}:{hz}" for r, (s, hz) in streams.items()],
            *[
                f"{names.absolute(names.robot_topic(r, names.POINTS_DRACO))}:={names.absolute(names.managed_cloud(r))}"
                for r in streams
            ],
        ],
        name,
    )


def start_limited_load(graphs, streams):
    """cps_transport's rate limiter per robot and the cloud load above them on the robots' side: the
    managed clouds the bandwidth manager sets the rates of (cps_harness's cloud_load node: its sizes and Hz)."""
    limiter = find_node("cps_transport", "rate_limiter")
    for r in streams:
        graphs.start(
            "phys",
            [
                sys.executable,
                limiter,
                "__name:=cloud_throttle",
                f"__ns:=/{r}",
                f"~input:={names.absolute(names.robot_topic(r, names.POINTS_DRACO))}",
                f"~output:={names.absolute(names.managed_cloud(r))}",
            ],
            f"limiter_{r}",
        )
    graphs.start(
        "phys",
        [sys.executable, CLOUD_LOAD, *[f"{r}:{s}:{hz}" for r, (s, hz) in streams.items()]],
        "load",
    )


def start_estimating_manager(graphs, robots, available_mbps, estimate_csv, *params):
    """The bandwidth manager on the twin's side with its online estimate, seeded with
    `available_mbps`, logging link_estimate.csv; managing `robots`' clouds only (no video)."""
    return graphs.start(
        "twin",
        [
            sys.executable,
            find_node("cps_bw_manager", "bandwidth_manager"),
            "__name:=bandwidth_manager",
            f"_robots:={','.join(robots)}",
            "_video_robots:=[]",
            f"_available_mbps:={available_mbps:.2f}",
            "_estimate_bandwidth:=true",
            f"_link_estimate_csv_path:={estimate_csv}",
            *params,
        ],
        "manager",
    )


def cpu_s(pids):
    return sum(process_cpu_s(pid) for pid in pids)


def bridge_pids(graphs):
    """The bridges' python processes (the netns exec wrapper execs into them)."""
    return [p.pid for p in graphs.bridges]


def teleop_latencies_ms(path):
    rows = [line.split() for line in open(path) if len(line.split()) == 2]
    return np.array([1000.0 * (float(recv) - float(sent)) for recv, sent in rows])


def teleop_under_saturation(graphs, path, seconds):
    """Teleop latencies (ms) twin -> robot at 20 Hz while the clouds saturate robots -> twin."""
    graphs.start("phys", [sys.executable, TELEOP_PROBE, "recv", "scout", path], "teleop_recv")
    start_load(graphs, SATURATING, "saturating_load")
    time.sleep(3.0)
    graphs.start("twin", [sys.executable, TELEOP_PROBE, "send", "scout", "20"], "teleop_send")
    time.sleep(seconds)
    return teleop_latencies_ms(path)
