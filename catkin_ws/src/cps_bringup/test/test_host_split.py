"""Host boundaries on one machine: --host-cpus parsing and refusals, and a real bringup that puts
each side's processes in its own cgroup (read back from /proc/<pid>/cgroup)."""

import os
import shutil
import signal
import subprocess

import pytest

from cps_bringup.host_split import (
    CONTROL_NICE,
    MAP_NICE,
    MISSION_SIDE_SHARES,
    HostSplit,
    HostSplitError,
    cgroup_v1_writable,
    default_host_cpus,
    parse_host_cpus,
    parse_host_quota,
)
from cps_bringup.plan import CONTROL_TIER, DIGITAL, PHYSICAL, NodeSpec
from cps_bringup.supervisor import Supervisor
from cps_harness.cgroups import group_exists, groups_of
from cps_harness.mission import BRINGUP, program_argv


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
        program_argv(BRINGUP, "all", "--host-cpus", "robots=0,twin=64", "--out", out),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode != 0 and "CPU 64 is not on this machine" in run.stderr, run.stderr
    assert not out.exists()


@pytest.mark.skipif(cgroup_v1_writable() is not None, reason=f"cgroup v1 split unavailable: {cgroup_v1_writable()}")
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs 2 CPUs to split")
def test_bringup_places_each_side_in_its_own_cgroup(reference_mission):
    """The reference mission (a --link run as root: split in halves by default): the simulator and
    the robots' tissue are in the robots' cpuset+cpu groups, the map server in the twin's, fleet
    control at CONTROL_NICE, the map server at MAP_NICE, each side on its own CPUs; the groups are
    gone after the run."""
    reference_mission.check()
    cpus = default_host_cpus(sorted(os.sched_getaffinity(0)))
    log, observed = reference_mission.log, reference_mission.observed
    assert "host split by cgroup v1 cpuset+cpu" in log, log[-3000:]
    assert observed.cgroups is not None and observed.cgroup_cpus is not None, observed.errors
    physical, digital = (" | ".join(observed.cgroups[s].values()) for s in (PHYSICAL, DIGITAL))
    assert "fleet_sim" in physical and "cloud_tissue" in physical and "map_server" not in physical, physical
    assert "map_server" in digital and "fleet_sim" not in digital and "cloud_tissue" not in digital, digital
    assert observed.cgroup_cpus == {side: ",".join(map(str, cpus[side])) for side in (PHYSICAL, DIGITAL)}
    # Each side weighs as a host against other work on its CPU, not as one process.
    shares = MISSION_SIDE_SHARES
    assert observed.cgroup_shares == {"": 2 * shares, PHYSICAL: shares, DIGITAL: shares}, observed.cgroup_shares
    assert observed.control_nice and all(n == CONTROL_NICE for n in observed.control_nice), observed.control_nice
    assert observed.map_server_nice == [MAP_NICE], observed.map_server_nice
    assert not group_exists(f"cpsfleet_{reference_mission.mission.pid}")


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
            assert groups_of(leftover.pid)["cpu"] == f"/{name}/{DIGITAL}"
            with open(f"/sys/fs/cgroup/cpuset/{name}/{DIGITAL}/cpuset.cpus") as f:
                assert f.read().strip() == str(cpus[1])
        assert leftover.poll() is None and groups_of(leftover.pid)["cpuset"] == "/"
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
                        tier=CONTROL_TIER,
                    )
                ],
                graph=None,
                side_prefix={PHYSICAL: ["ip", "netns", "exec", netns]},
                spec_prefix=lambda spec: split.prefix(spec.side, tier=spec.tier),
            )
            argv = supervisor.argv_of(supervisor.specs[0])
            run = subprocess.run(argv, capture_output=True, text=True, timeout=30)
        assert run.returncode == 0, run.stderr
        group, nice = run.stdout.split()
        assert group.endswith(f":cpuset:/{name}/{PHYSICAL}") and int(nice) == CONTROL_NICE
    finally:
        subprocess.run(["ip", "netns", "del", netns])
