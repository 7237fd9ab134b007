"""The real fleet_sim in a benchmark, as video_live_bench and fleet_sim_bench run it (bench/ only):
start it on a private master and wait for its robots, then measure its CPU and its sensor
workers' from /proc over a window after a warm-up. Imported by scripts run as
`python bench/<name>.py`, whose own folder is first on sys.path."""

import time

from cps_fleet import names
from cps_ros.processes import process_cpu_s

# The benchmarks' fleet_sim: the light sensor profile and the fast renderer.
FLEET_SIM_PARAMS = {"~profile": "light", "~renderer": "fast"}
# How long fleet_sim may take to publish its last robot's odometry (a loaded 2-core machine).
READY_TIMEOUT_S = 180


def children(pid):
    """The pids of `pid`'s child processes (fleet_sim's sensor workers)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as stream:
            return [int(c) for c in stream.read().split()]
    except FileNotFoundError:
        return []


def start_fleet_sim(node_graph, fleet, name, params=None, env=None):
    """fleet_sim named `name` on `node_graph` (FLEET_SIM_PARAMS and `params`) for `fleet`, once its
    last robot's odometry is out; its process."""
    proc = node_graph.start_node(
        "cps_sim", "fleet_sim", name=name, env=env, params={**FLEET_SIM_PARAMS, **(params or {})}
    )
    node_graph.wait_for_topic(
        names.absolute(names.robot_topic(fleet.robots[-1].name, names.ODOM)), timeout_s=READY_TIMEOUT_S
    )
    return proc


def measure_cpu(proc, warmup_s, seconds, measuring):
    """After `warmup_s`, `measuring` set for `seconds`; the CPU of `proc` and of its children then
    (core-s per s), {pid: ...}, `proc` first."""
    time.sleep(warmup_s)
    pids = [proc.pid] + children(proc.pid)
    cpu0 = {pid: process_cpu_s(pid) for pid in pids}
    measuring.set()
    time.sleep(seconds)
    measuring.clear()
    return {pid: (process_cpu_s(pid) - cpu0[pid]) / seconds for pid in pids}
