"""Host boundaries on one machine: the robots' side and the twin side on separate CPU budgets.

On a real site every robot has its own computer and the twin its own server; on one test machine
the simulation would otherwise starve the twin. As root, each side gets a cgroup v1 group under
the `cpuset` controller (its own CPUs) and the `cpu` controller (optionally a CFS quota, in cores);
every node of the side is started inside them by an `sh` prefix that writes its own pid into both
groups and then execs the node (children inherit the groups). Without root, or without a writable
cgroup v1 hierarchy, the split falls back to `taskset` (CPUs only, no quota), or to no split when
the machine has a single CPU, and `describe` says which.

Priority: control processes (velocity mux, route control, the shared fleet control, each side's
command-lane bridge) run at nice CONTROL_NICE and the map server at MAP_NICE (higher priority than
the sensors, clouds, GUI and statistics of their side, which stay at 0). We choose nice rather than
SCHED_RR: a real-time task inside a cgroup v1 `cpu` group needs an `rt_runtime_us` budget carved for
that group, and a busy real-time node could starve its whole side; a nice of -10 gives a control
node ~10x the CFS weight of a sensor node when they compete, -5 the map server ~3x. Lowering nice
needs root; without it the priorities stay equal (said by `describe`).
"""

import dataclasses
import os
import shutil
import sys
import time
from typing import Dict, List, Optional, Tuple

from cps_bringup.plan import CONTROL_TIER, DIGITAL, MAP_TIER, NORMAL_TIER, PHYSICAL
from cps_ros.processes import end_processes, process_command, process_running

# What the user writes on the command line -> the plan's side.
SIDE_NAMES = {"robots": PHYSICAL, "twin": DIGITAL}
CGROUP_ROOT = "/sys/fs/cgroup"
CONTROL_NICE = -10
# The map server above the twin's other nodes: at 0 beside the GUI, the bridge and the statistics on
# a loaded twin CPU its clouds waited 1-2 s to be inserted and the published map went over 3 s old
# (the reference mission's verdict FAILED in CI, 2026-11-29). The reference mission beside two busy
# loops, its published map's oldest while the robots worked: 2.7 and 3.3 s at 0; 2.0, 2.1, 2.3 s at -5.
MAP_NICE = -5
TIER_NICE = {CONTROL_TIER: CONTROL_NICE, MAP_TIER: MAP_NICE, NORMAL_TIER: 0}
CFS_PERIOD_US = 100_000
MAX_CPU_SHARES = 262144  # the kernel's bound on cpu.shares
# Each side's cpu.shares in a mission (8 plain processes' weight): a side stands for a host whose
# 8-17 nodes would each weigh 1024 without the split, so other work on the same CPUs (another
# test worker, a benchmark's load) must not weigh as much as the whole side. At the default 1024
# the run's group weighed as one process, and a reference mission beside one busy test process
# got half its twin CPU and failed its map-freshness bar (2026-11-28).
MISSION_SIDE_SHARES = 8192
REMOVE_SETTLE_S = 2.0  # an exiting process holds its group until reaped: milliseconds, not seconds
# How long a dead run's leftover process has between SIGTERM and SIGKILL (a node saves its map).
STALE_TERM_GRACE_S = 3.0

# Writes the shell's own pid into every group given, then execs the node (argv after the groups).
_JOIN = 'n=$1; shift; i=0; while [ $i -lt $n ]; do echo $$ > "$1/cgroup.procs" || exit 126; shift; i=$((i+1)); done; exec "$@"'


class HostSplitError(ValueError):
    """A --host-cpus or --host-quota the machine cannot honour; nothing was started."""


def online_cpus() -> Tuple[int, ...]:
    """The CPUs this process may run on."""
    return tuple(sorted(os.sched_getaffinity(0)))


def _cpu_list(text, where):
    cpus = []
    for part in text.split("+"):
        part = part.strip()
        try:
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                cpus.extend(range(lo, hi + 1))
            else:
                cpus.append(int(part))
        except ValueError:
            raise HostSplitError(f"{where}: '{part}' is not a CPU number or range (e.g. 0, 0-1, 0+2)") from None
    return cpus


def parse_host_cpus(text: str, available=None) -> Dict[str, Tuple[int, ...]]:
    """`robots=0,twin=1` (a side's CPUs: numbers, ranges `0-2`, joined by `+` or by further commas,
    `robots=0,1,twin=2`) -> {side: CPUs}. HostSplitError for a CPU the machine lacks, a side left
    with none, a CPU in both sides or an unknown side."""
    available = tuple(available if available is not None else online_cpus())
    sides: Dict[str, List[int]] = {}
    current = None
    for token in (t.strip() for t in text.split(",")):
        if not token:
            continue
        if "=" in token:
            name, cpus = (x.strip() for x in token.split("=", 1))
            if name not in SIDE_NAMES:
                raise HostSplitError(f"--host-cpus: unknown side '{name}' (sides: {', '.join(SIDE_NAMES)})")
            current = SIDE_NAMES[name]
            if current in sides:
                raise HostSplitError(f"--host-cpus: side '{name}' given twice")
            sides[current] = []
            if not cpus:
                continue
            token = cpus
        elif current is None:
            raise HostSplitError(f"--host-cpus: '{token}' before any side (write robots=CPUS,twin=CPUS)")
        sides[current].extend(_cpu_list(token, "--host-cpus"))
    for side_name, side in SIDE_NAMES.items():
        if not sides.get(side):
            raise HostSplitError(
                f"--host-cpus '{text}' leaves the {side_name} side with no CPU (write robots=CPUS,twin=CPUS)"
            )
    for side, cpus in sides.items():
        missing = sorted(set(cpus) - set(available))
        if missing:
            raise HostSplitError(
                f"--host-cpus: CPU {', '.join(map(str, missing))} is not on this machine "
                f"(CPUs this process may use: {', '.join(map(str, available))})"
            )
    shared = set(sides[PHYSICAL]) & set(sides[DIGITAL])
    if shared:
        raise HostSplitError(f"--host-cpus: CPU {', '.join(map(str, sorted(shared)))} is in both sides")
    return {side: tuple(sorted(set(cpus))) for side, cpus in sides.items()}


def parse_host_quota(text: str, cpus: Dict[str, Tuple[int, ...]]) -> Dict[str, float]:
    """`twin=0.5` -> {side: cores of CFS quota}; at most the side's CPU count, above 0."""
    quota = {}
    for token in (t.strip() for t in text.split(",") if t.strip()):
        name, _, value = token.partition("=")
        if name.strip() not in SIDE_NAMES:
            raise HostSplitError(f"--host-quota: unknown side '{name}' (sides: {', '.join(SIDE_NAMES)})")
        side = SIDE_NAMES[name.strip()]
        try:
            cores = float(value)
        except ValueError:
            raise HostSplitError(f"--host-quota: '{value}' is not a number of cores") from None
        limit = len(cpus.get(side, ())) or len(online_cpus())
        if not 0 < cores <= limit:
            raise HostSplitError(f"--host-quota: {name}={value}: a quota is in (0, {limit}] cores for that side")
        quota[side] = cores
    return quota


def default_host_cpus(available=None) -> Optional[Dict[str, Tuple[int, ...]]]:
    """The default split for link runs: the twin gets the last half of the CPUs (rounded down, at
    least one), the robots the rest; None on a single-CPU machine."""
    available = tuple(available if available is not None else online_cpus())
    if len(available) < 2:
        return None
    twin = max(1, len(available) // 2)
    return {PHYSICAL: available[:-twin], DIGITAL: available[-twin:]}


def cgroup_v1_writable(root=CGROUP_ROOT):
    """None when this process can create cpuset and cpu groups, else why not."""
    if os.geteuid() != 0:
        return "not root"
    for controller, probe in (("cpuset", "cpuset.cpus"), ("cpu", "cpu.cfs_quota_us")):
        path = os.path.join(root, controller)
        if not os.path.isfile(os.path.join(path, probe)):
            return f"no cgroup v1 '{controller}' controller at {path}"
        if not os.access(path, os.W_OK):
            return f"{path} is not writable"
    return None


@dataclasses.dataclass
class HostSplit:
    """The sides' CPU budgets for one run; a context manager that creates and removes the groups."""

    cpus: Dict[str, Tuple[int, ...]]
    quota_cores: Dict[str, float] = dataclasses.field(default_factory=dict)
    name: str = "cpsfleet"
    root: str = CGROUP_ROOT
    mode: str = "cgroup"  # "cgroup" | "taskset" | "none"
    reason: str = ""  # why not "cgroup"
    can_raise_priority: bool = dataclasses.field(default_factory=lambda: os.geteuid() == 0)
    # cpu.shares per side (default 1024, a plain process's weight): against processes outside the
    # groups on the same CPUs (other work on a shared test machine), a side with more shares gets
    # the CPU first.
    shares: Dict[str, int] = dataclasses.field(default_factory=dict)

    @classmethod
    def choose(cls, cpus, quota_cores=None, name="cpsfleet", root=CGROUP_ROOT, shares=None):
        """cgroups where they are writable, else taskset, else none (cpus None: no split)."""
        quota_cores = quota_cores or {}
        if cpus is None:
            return cls({}, {}, name, root, mode="none", reason="a single CPU: nothing to split")
        why = cgroup_v1_writable(root)
        if why is None:
            return cls(cpus, quota_cores, name, root, shares=dict(shares or {}))
        if shutil.which("taskset"):
            return cls(cpus, {}, name, root, mode="taskset", reason=why)
        return cls({}, {}, name, root, mode="none", reason=f"{why}, and no taskset")

    def group(self, controller, side):
        return os.path.join(self.root, controller, self.name, side)

    def __enter__(self):
        if self.mode != "cgroup":
            return self
        self._remove_stale()
        if any(os.path.isdir(os.path.join(self.root, c, self.name)) for c in ("cpuset", "cpu")):
            self._remove()  # a previous run killed hard left them
        try:
            for controller in ("cpuset", "cpu"):
                os.makedirs(os.path.join(self.root, controller, self.name), exist_ok=True)
            if self.shares:
                # The sides' groups sit in the run's group, and that one competes with the processes
                # outside it: without its own weight (1024, one plain process's) the sides' shares
                # only weigh them against each other (a twin at 16384 shares got half its CPU
                # beside one busy process of other work; issue 37).
                parent_shares = min(sum(int(v) for v in self.shares.values()), MAX_CPU_SHARES)
                _write(os.path.join(self.root, "cpu", self.name, "cpu.shares"), str(parent_shares))
            parent = os.path.join(self.root, "cpuset", self.name)
            all_cpus = sorted({c for cpus in self.cpus.values() for c in cpus})
            mems = _read(os.path.join(self.root, "cpuset", "cpuset.mems"))
            _write(os.path.join(parent, "cpuset.cpus"), ",".join(map(str, all_cpus)))
            _write(os.path.join(parent, "cpuset.mems"), mems)
            for side, cpus in self.cpus.items():
                os.makedirs(self.group("cpuset", side), exist_ok=True)
                _write(os.path.join(self.group("cpuset", side), "cpuset.cpus"), ",".join(map(str, cpus)))
                _write(os.path.join(self.group("cpuset", side), "cpuset.mems"), mems)
                os.makedirs(self.group("cpu", side), exist_ok=True)
                if side in self.shares:
                    _write(os.path.join(self.group("cpu", side), "cpu.shares"), str(int(self.shares[side])))
                quota = self.quota_cores.get(side)
                if quota:
                    _write(os.path.join(self.group("cpu", side), "cpu.cfs_period_us"), str(CFS_PERIOD_US))
                    _write(os.path.join(self.group("cpu", side), "cpu.cfs_quota_us"), str(int(quota * CFS_PERIOD_US)))
        except OSError as exc:
            self._remove()
            raise HostSplitError(f"could not create the sides' cgroups under {self.root}: {exc}") from exc
        return self

    def __exit__(self, *exc):
        try:
            self._remove()
        except HostSplitError as err:
            if exc[0] is None:
                raise
            print(f"host split: {err}", file=sys.stderr)  # do not hide the error the run ended with

    def _remove_stale(self, grace_s=STALE_TERM_GRACE_S):
        """Remove the groups of earlier runs (`<prefix>_<pid>`) whose bringup died without cleaning up
        (SIGKILL): their pid is gone or a zombie. What still runs in them is that run's leftovers (a
        node that hung in its shutdown, the GUI's X server): each gets SIGTERM, then SIGKILL after
        `grace_s`, as systemd stops a unit's control group, and is named on stderr."""
        prefix, _, own_pid = self.name.rpartition("_")
        if not prefix or not own_pid.isdigit():
            return
        tops = []
        for controller in ("cpuset", "cpu"):
            folder = os.path.join(self.root, controller)
            for entry in os.listdir(folder):
                head, _, pid = entry.rpartition("_")
                if head == prefix and pid.isdigit() and pid != own_pid and not process_running(int(pid)):
                    tops.append(os.path.join(folder, entry))
        groups = [os.path.join(top, s) for top in tops for s in os.listdir(top) if os.path.isdir(os.path.join(top, s))]
        leftovers = {int(pid) for g in groups + tops for pid in _read(os.path.join(g, "cgroup.procs")).split()}
        if leftovers:
            print(
                f"host split: ending {len(leftovers)} process(es) left in {', '.join(sorted(tops))} by a "
                f"run that is gone: {'; '.join(f'{pid} {process_command(pid)}' for pid in sorted(leftovers))}",
                file=sys.stderr,
            )
            end_processes(leftovers, grace_s, kill_wait_s=REMOVE_SETTLE_S)
        for g in groups + tops:
            try:
                os.rmdir(g)
            except OSError as exc:
                print(f"host split: could not remove {g}, left by a run that is gone: {exc}", file=sys.stderr)

    def _remove(self, settle_s=REMOVE_SETTLE_S):
        """Remove the groups; a group still holding a process (a node that outlived stop_all) has its
        tasks moved to the root group first, so that nothing is left behind. A process that is
        exiting cannot be moved and keeps its group busy until it is reaped, so the removal is
        retried for up to `settle_s`; what still remains after that is named in the error."""
        deadline = time.monotonic() + settle_s
        while True:
            busy = self._remove_once()
            if not busy:
                return
            if time.monotonic() >= deadline:
                raise HostSplitError(
                    "could not remove the sides' cgroups, still holding processes: "
                    + "; ".join(f"{folder}: {pids or 'a child group'}" for folder, pids in busy)
                )
            time.sleep(0.02)

    def _remove_once(self):
        """One pass over both controllers: move every task to the root group, then remove the groups
        bottom-up. Returns the (group, pids) that could not be removed."""
        busy = []
        for controller in ("cpuset", "cpu"):
            top = os.path.join(self.root, controller, self.name)
            if not os.path.isdir(top):
                continue
            for folder in [os.path.join(top, s) for s in os.listdir(top) if os.path.isdir(os.path.join(top, s))] + [
                top
            ]:
                for pid in _read(os.path.join(folder, "cgroup.procs")).split():
                    try:
                        _write(os.path.join(self.root, controller, "cgroup.procs"), pid)
                    except OSError:
                        pass  # it ended meanwhile
                try:
                    os.rmdir(folder)
                except FileNotFoundError:
                    pass
                except OSError:
                    busy.append((folder, _read(os.path.join(folder, "cgroup.procs")).replace("\n", " ")))
        return busy

    def prefix(self, side, tier=NORMAL_TIER) -> List[str]:
        """argv that starts a node of `side` inside its budget, at its tier's nice (TIER_NICE)."""
        argv: List[str] = []
        if self.mode == "cgroup" and side in self.cpus:
            groups = [self.group("cpuset", side), self.group("cpu", side)]
            argv += ["sh", "-c", _JOIN, "cps-host-split", str(len(groups)), *groups]
        elif self.mode == "taskset" and side in self.cpus:
            argv += ["taskset", "-c", ",".join(map(str, self.cpus[side]))]
        if TIER_NICE[tier] and self.can_raise_priority:
            argv += ["nice", "-n", str(TIER_NICE[tier])]
        return argv

    def describe(self):
        """What the report says about the split."""
        sides = "; ".join(
            f"{'robots' if side == PHYSICAL else 'twin'} CPU {','.join(map(str, cpus))}"
            + (f" (quota {self.quota_cores[side]:g} cores)" if side in self.quota_cores else "")
            + (f" (cpu.shares {self.shares[side]})" if side in self.shares and self.mode == "cgroup" else "")
            for side, cpus in sorted(self.cpus.items(), reverse=True)
        )
        priority = (
            f"control nodes at nice {CONTROL_NICE}, the map server at {MAP_NICE}"
            if self.can_raise_priority
            else "control nodes and the map server at the same priority as the others (lowering nice needs root)"
        )
        if self.mode == "cgroup":
            return f"host split by cgroup v1 cpuset+cpu ({self.root}/{{cpuset,cpu}}/{self.name}): {sides}; {priority}"
        if self.mode == "taskset":
            return f"host split by taskset only (no cgroups: {self.reason}; no quota): {sides}; {priority}"
        return f"NO host split ({self.reason}): both sides share every CPU; {priority}"


def _read(path):
    with open(path) as f:
        return f.read().strip()


def _write(path, text):
    with open(path, "w") as f:
        f.write(text)
