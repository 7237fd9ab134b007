"""Host boundaries on one machine: --host-cpus parsing and refusals, and a real bringup that puts
each side's processes in its own cgroup (read back from /proc/<pid>/cgroup)."""

import os
import shutil
import signal
import subprocess
import sys

import pytest

from cps_bringup.host_split import (
    CONTROL_NICE,
    HostSplit,
    HostSplitError,
    cgroup_v1_writable,
    default_host_cpus,
    parse_host_cpus,
    parse_host_quota,
)
from cps_bringup.plan import DIGITAL, PHYSICAL, NodeSpec
from cps_bringup.supervisor import Supervisor

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")
MISSION_S = 20


def test_host_cpus_are_parsed_per_side():
    assert parse_host_cpus("robots=0,twin=1", available=(0, 1)) == {PHYSICAL: (0,), DIGITAL: (1,)}
    assert parse_host_cpus("robots=0,1,twin=2-3", available=range(4)) == {PHYSICAL: (0, 1), DIGITAL: (2, 3)}
    assert parse_host_cpus("twin=3,robots=0+2", available=range(4)) == {PHYSICAL: (0, 2), DIGITAL: (3,)}


@pytest.mark.parametrize(
    "text, words",
    [
        ("robots=0,twin=7", "CPU 7 is not on this machine"),
        ("robots=0", "leaves the twin side with no CPU"),
        ("robots=,twin=1", "leaves the robots side with no CPU"),
        ("robots=0,twin=0", "in both sides"),
        ("robots=0,cloud=1", "unknown side"),
        ("robots=a,twin=1", "not a CPU number"),
    ],
)
def test_bad_host_cpus_are_refused(text, words):
    with pytest.raises(HostSplitError, match=words):
        parse_host_cpus(text, available=(0, 1))


def test_quota_and_default_split():
    cpus = {PHYSICAL: (0,), DIGITAL: (1,)}
    assert parse_host_quota("twin=0.5", cpus) == {DIGITAL: 0.5}
    with pytest.raises(HostSplitError, match=r"\(0, 1\] cores"):
        parse_host_quota("twin=2", cpus)
    assert default_host_cpus((0, 1)) == cpus
    assert default_host_cpus((0, 1, 2, 3)) == {PHYSICAL: (0, 1), DIGITAL: (2, 3)}
    assert default_host_cpus((0,)) is None
    assert "NO host split" in HostSplit.choose(None).describe()


def test_bringup_refuses_a_missing_cpu_before_anything_starts(open_tmp_path):
    out = open_tmp_path / "refused"
    run = subprocess.run(
        [sys.executable, BRINGUP, "all", "--host-cpus", "robots=0,twin=64", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode != 0 and "CPU 64 is not on this machine" in run.stderr, run.stderr
    assert not out.exists()


def _groups_of(pid):
    """{controller: group path} of a process, None if it ended."""
    try:
        with open(f"/proc/{pid}/cgroup") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    return {ctl: path for _, ctls, path in (line.split(":", 2) for line in lines) for ctl in ctls.split(",")}


def _cmdline(pid):
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _members(group_name):
    """{side: {pid: cmdline}} of every process in the run's cpuset groups."""
    members = {PHYSICAL: {}, DIGITAL: {}}
    for pid in (int(p) for p in os.listdir("/proc") if p.isdigit()):
        groups = _groups_of(pid)
        for side in members:
            if groups and groups.get("cpuset") == f"/{group_name}/{side}":
                assert groups.get("cpu") == f"/{group_name}/{side}", (pid, groups)
                members[side][pid] = _cmdline(pid)
    return members


def _nice(pid):
    with open(f"/proc/{pid}/stat") as f:
        return int(f.read().rsplit(")", 1)[1].split()[16])


@pytest.mark.ros
@pytest.mark.slow
@pytest.mark.skipif(cgroup_v1_writable() is not None, reason=f"cgroup v1 split unavailable: {cgroup_v1_writable()}")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs to split")
def test_bringup_places_each_side_in_its_own_cgroup(bringup_mission):
    """A one-robot mission with --host-cpus robots=0,twin=1: the simulator and the robot's tissue are
    in the robots' cpuset+cpu groups (CPU 0), the map server in the twin's (CPU 1), fleet control at
    CONTROL_NICE; the groups are gone after the run."""
    cpus = sorted(os.sched_getaffinity(0))[:2]

    def read_groups(mission):
        """(members, cpus read per side, nice of fleet control) of the run's groups."""
        group = f"cpsfleet_{mission.pid}"
        members, cpus_read = _members(group), {}
        for side in members:
            with open(f"/sys/fs/cgroup/cpuset/{group}/{side}/cpuset.cpus") as f:
                cpus_read[side] = f.read().strip()
        control = [p for p, cmd in members[PHYSICAL].items() if "fleet_control" in cmd and "nice" not in cmd]
        return members, cpus_read, [_nice(p) for p in control]

    args = ["--robots", "scout", "--host-cpus", f"robots={cpus[0]},twin={cpus[1]}"]
    mission = bringup_mission("split", args, read_groups, MISSION_S)
    assert "host split by cgroup v1 cpuset+cpu" in mission.log, mission.log[-3000:]
    assert mission.read_while_up is not None, mission.log[-3000:]
    members, cpus_read, nice = mission.read_while_up
    physical, digital = (" | ".join(members[s].values()) for s in (PHYSICAL, DIGITAL))
    assert "fleet_sim" in physical and "cloud_tissue" in physical and "map_server" not in physical, physical
    assert "map_server" in digital and "fleet_sim" not in digital and "cloud_tissue" not in digital, digital
    assert cpus_read == {PHYSICAL: str(cpus[0]), DIGITAL: str(cpus[1])}
    assert nice and all(n == CONTROL_NICE for n in nice), (nice, physical)
    for controller in ("cpuset", "cpu"):
        assert not os.path.exists(f"/sys/fs/cgroup/{controller}/cpsfleet_{mission.pid}")


@pytest.mark.skipif(cgroup_v1_writable() is not None, reason=f"cgroup v1 split unavailable: {cgroup_v1_writable()}")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs to split")
@pytest.mark.skipif(cgroup_v1_writable() is not None, reason=f"cgroup v1 split unavailable: {cgroup_v1_writable()}")
def test_the_sides_shares_weigh_against_other_work_too():
    """The run's group carries the sides' shares summed: otherwise it weighs as one plain process
    against everything outside it, whatever the sides ask."""
    cpus = sorted(os.sched_getaffinity(0))
    name = f"cpsfleet_shares_{os.getpid()}"
    sides = {PHYSICAL: (cpus[0],), DIGITAL: (cpus[-1],)}
    with HostSplit.choose(sides, name=name, shares={PHYSICAL: 2048, DIGITAL: 16384}):
        read = {
            group: open(f"/sys/fs/cgroup/cpu/{name}{group}/cpu.shares").read().strip()
            for group in ("", f"/{PHYSICAL}", f"/{DIGITAL}")
        }
    assert read == {"": "18432", f"/{PHYSICAL}": "2048", f"/{DIGITAL}": "16384"}
    assert not os.path.exists(f"/sys/fs/cgroup/cpu/{name}")


def test_groups_are_removed_even_with_a_process_left_inside_and_stale_ones_too():
    """A node that outlived the run is moved out and the groups removed; an earlier run's groups
    (its bringup killed hard, pid gone) are removed at the next start, and what it left running in
    them ended: SIGTERM, then SIGKILL for one that ignores SIGTERM."""
    cpus = sorted(os.sched_getaffinity(0))[:2]
    stale = "/sys/fs/cgroup/cpu/cpsfleet_4194305/physical"  # above any pid_max: that bringup is gone
    os.makedirs(stale, exist_ok=True)
    stale_leftover = subprocess.Popen(["sh", "-c", 'trap "" TERM; exec sleep 60'])
    with open(os.path.join(stale, "cgroup.procs"), "w") as procs:
        procs.write(str(stale_leftover.pid))
    name = f"cpsfleet_{os.getpid()}"
    leftover = None
    try:
        with HostSplit.choose({PHYSICAL: (cpus[0],), DIGITAL: (cpus[1],)}, name=name) as split:
            assert not os.path.exists(os.path.dirname(stale))
            assert stale_leftover.wait(5) == -signal.SIGKILL
            # The node says where it runs (one line of its own /proc/self/cgroup), then stays.
            leftover = subprocess.Popen(
                [*split.prefix(DIGITAL), "sh", "-c", "grep :cpuset: /proc/self/cgroup; exec cat"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
            assert leftover.stdout.readline().strip().endswith(f":cpuset:/{name}/{DIGITAL}")
            assert _groups_of(leftover.pid)["cpu"] == f"/{name}/{DIGITAL}"
            with open(f"/sys/fs/cgroup/cpuset/{name}/{DIGITAL}/cpuset.cpus") as f:
                assert f.read().strip() == str(cpus[1])
        assert leftover.poll() is None and _groups_of(leftover.pid)["cpuset"] == "/"
        for controller in ("cpuset", "cpu"):
            assert not os.path.exists(f"/sys/fs/cgroup/{controller}/{name}")
    finally:
        for process in (leftover, stale_leftover):
            if process is not None and process.poll() is None:
                process.kill()
                process.wait()
        for folder in (stale, os.path.dirname(stale)):
            if os.path.isdir(folder):
                os.rmdir(folder)


@pytest.mark.skipif(cgroup_v1_writable() is not None, reason=f"cgroup v1 split unavailable: {cgroup_v1_writable()}")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs to split")
@pytest.mark.skipif(shutil.which("ip") is None, reason="no iproute2")
def test_a_node_started_through_ip_netns_exec_keeps_its_group_and_priority():
    """With --link the robots' nodes start through `ip netns exec`, which mounts its own /sys: the
    supervisor puts the split's prefix before it (joined first, inherited through it)."""
    cpus = sorted(os.sched_getaffinity(0))[:2]
    netns = f"cpshosttest{os.getpid()}"
    name = f"cpsfleet_{os.getpid()}"
    subprocess.run(["ip", "netns", "add", netns], check=True)
    try:
        with HostSplit.choose({PHYSICAL: (cpus[0],), DIGITAL: (cpus[1],)}, name=name) as split:
            supervisor = Supervisor(
                [
                    NodeSpec(
                        "probe",
                        PHYSICAL,
                        ("sh", "-c", "grep :cpuset: /proc/self/cgroup; cut -d' ' -f19 /proc/self/stat"),
                        control=True,
                    )
                ],
                graph=None,
                side_prefix={PHYSICAL: ["ip", "netns", "exec", netns]},
                spec_prefix=lambda spec: split.prefix(spec.side, control=spec.control),
            )
            argv = supervisor.argv_of(supervisor.specs[0])
            run = subprocess.run(argv, capture_output=True, text=True, timeout=30)
        assert run.returncode == 0, run.stderr
        group, nice = run.stdout.split()
        assert group.endswith(f":cpuset:/{name}/{PHYSICAL}") and int(nice) == CONTROL_NICE
    finally:
        subprocess.run(["ip", "netns", "del", netns])
