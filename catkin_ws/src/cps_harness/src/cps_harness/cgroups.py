"""Read back where a running mission's processes are: the host split's cgroup v1 groups
(`/sys/fs/cgroup/{cpuset,cpu}/<group>/<side>`), their CPUs, and a process's nice."""

import os

from cps_bringup.plan import DIGITAL, PHYSICAL
from cps_ros.processes import process_command

SIDES = (PHYSICAL, DIGITAL)


def groups_of(pid):
    """{controller: group path} of a process, None if it ended."""
    try:
        with open(f"/proc/{pid}/cgroup") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    return {ctl: path for _, ctls, path in (line.split(":", 2) for line in lines) for ctl in ctls.split(",")}


def members_of_split(group_name):
    """{side: {pid: cmdline}} of every process in the run's cpuset groups; AssertionError if one of
    them is in a cpu group other than its cpuset's."""
    members = {side: {} for side in SIDES}
    for pid in (int(p) for p in os.listdir("/proc") if p.isdigit()):
        groups = groups_of(pid)
        for side in members:
            if groups and groups.get("cpuset") == f"/{group_name}/{side}":
                assert groups.get("cpu") == f"/{group_name}/{side}", (pid, groups)
                members[side][pid] = process_command(pid, max_chars=4096)
    return members


def group_cpus(group_name):
    """{side: cpuset.cpus} of the run's groups."""
    cpus = {}
    for side in SIDES:
        with open(f"/sys/fs/cgroup/cpuset/{group_name}/{side}/cpuset.cpus") as f:
            cpus[side] = f.read().strip()
    return cpus


def group_shares(group_name):
    """{side: cpu.shares} of the run's groups, and the run's own group's under "" (their sum)."""
    shares = {}
    for side in ("", *SIDES):
        with open(os.path.join("/sys/fs/cgroup/cpu", group_name, side, "cpu.shares")) as f:
            shares[side] = int(f.read().strip())
    return shares


def nice_of(pid):
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])  # field 19 of stat: nice


def _nice_of_node(members, side, node):
    """The nice of every process of `side` running `node` (not its `nice` wrapper, not a warm spare)."""
    return [
        nice_of(p)
        for p, cmd in members.get(side, {}).items()
        if node in cmd and "nice" not in cmd and "spare" not in cmd
    ]


def control_nice(members):
    """The nice of every fleet_control process of the robots' side."""
    return _nice_of_node(members, PHYSICAL, "fleet_control")


def map_server_nice(members):
    """The nice of the twin's map server process(es)."""
    return _nice_of_node(members, DIGITAL, "cps_mapping/nodes/map_server")


def group_exists(group_name):
    return any(os.path.exists(f"/sys/fs/cgroup/{controller}/{group_name}") for controller in ("cpuset", "cpu"))
