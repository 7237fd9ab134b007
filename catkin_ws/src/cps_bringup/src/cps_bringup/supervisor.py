"""Start the planned processes against a master, wait until each is up, restart what dies, stop all.

The supervisor knows processes and topics, nothing of what the nodes do. Up means: the process
runs and every topic in its spec is advertised. A node that does not come up within the timeout
is named in the error, with the end of its log. Restarts wait an exponential backoff and a node's
restart limit counts within a time window (`RestartPolicy`); a node that is not essential (the GUI)
may end without ending the run. A node whose spec asks for it has a warm spare (cps_ros.spare)
once the run is up: its restart starts the spare, its imports done, and a new spare follows. The
master is watched: `MasterLost` when it is gone. Started as root, the nodes run as `run_as` (see
`cps_bringup.privileges`).
"""

import contextlib
import dataclasses
import math
import os
import select
import shutil
import time
from typing import Callable, Dict, List, Optional

from cps_bringup.plan import NodeSpec
from cps_ros import spare as spares
from cps_ros.processes import RosGraph, stop_all

# A spare is started this long after its node is up (the run's start, or a restart that used the
# previous one): its imports take a CPU second that the node's own start-up needs first, s.
SPARE_AFTER_UP_S = 5.0
# A spare imports at nice SPARE_NICE (cps_ros.spare); one still importing this long after its start is given
# its node's priority (as root): on a saturated side it would never finish (a chaos soak's robots'
# spares), and a restart without a ready spare took 4-6 s to start cloud_tissue there. Long enough
# that a mission's first minutes, when the robots' side is busiest, never pay for it (at 30 s the
# promotions fell inside the suite's missions; final36's monitoring mission found its change late,
# not traced), s.
SPARE_PROMOTE_AFTER_S = 120.0
# A spare stops at once (nothing to save): SIGINT, then SIGTERM after this, s.
SPARE_STOP_TIMEOUT_S = 1.0


class BringupError(RuntimeError):
    """The system could not be brought up or kept up; the message says what and why."""


class MasterLost(BringupError):
    """The ROS master is gone: nodes can no longer find each other."""


def restart_note(code, restarts_in_window, restart_limit, delay_s):
    """The event of a restart scheduled after a death (read back from the run's log by
    cps_harness.chaos.RestartBudget)."""
    return f"exited with code {code}; restart {restarts_in_window}/{restart_limit} in {delay_s:.1f} s"


@dataclasses.dataclass(frozen=True)
class RestartPolicy:
    """Delay before the n-th restart within `window_s`: backoff_s * 2^(n-1), at most backoff_max_s.
    The default restarts at once and counts over the whole run."""

    backoff_s: float = 0.0
    backoff_max_s: float = 0.0
    window_s: float = math.inf

    @classmethod
    def from_limits(cls, limits):
        return cls(limits.restart_backoff_s, limits.restart_backoff_max_s, limits.restart_window_s)

    def delay_s(self, restarts_in_window):
        return min(self.backoff_s * 2 ** max(restarts_in_window - 1, 0), self.backoff_max_s)


@dataclasses.dataclass
class Event:
    time_s: float
    label: str
    what: str


@dataclasses.dataclass
class _Running:
    spec: NodeSpec
    proc: object
    restarts: int = 0
    up: bool = False
    restart_times: List[float] = dataclasses.field(default_factory=list)
    restart_at: Optional[float] = None
    ended: bool = False
    # s from start_all's call to this node's start: how long it waited for the nodes it comes after.
    waited_s: float = 0.0
    spare: Optional[object] = None  # its warm spare's process, waiting (spec.spare)
    spare_due: Optional[float] = None  # when the next spare starts, once the node is up
    spare_promote_at: Optional[float] = None  # when a spare still importing gets the node's priority


class Supervisor:
    """Runs `specs` on `graph`'s master. `side_prefix`/`side_env` put a side into a namespace;
    `side_graphs` gives a side its own master (a RosGraph-like object: popen, published_topics,
    output, stop), e.g. the robots' master when the twins are joined by Zenoh bridges."""

    def __init__(
        self,
        specs: List[NodeSpec],
        graph: RosGraph,
        side_prefix: Optional[Dict[str, List[str]]] = None,
        side_env: Optional[Dict[str, Dict[str, str]]] = None,
        log=print,
        policy: RestartPolicy = RestartPolicy(),
        node_log_max_bytes: Optional[int] = None,
        user_prefix: Optional[List[str]] = None,
        clock: Callable[[], float] = time.monotonic,
        side_graphs: Optional[Dict[str, object]] = None,
        spec_prefix: Optional[Callable[[NodeSpec], List[str]]] = None,
        warm_spares: bool = False,
    ):
        """`user_prefix`: argv that runs a node as another user (after the side's prefix). `side_graphs`:
        a side's own master (Zenoh: a master per side), instead of `graph`. `spec_prefix(spec)`: argv
        before the side's prefix (its side's CPU budget and priority: host_split). `warm_spares`: keep
        a spare of each node whose spec asks for one."""
        labels = [s.label for s in specs]
        if len(set(labels)) != len(labels):
            raise ValueError(f"duplicate node labels in the plan: {labels}")
        self.specs = specs
        self.graph = graph
        self.side_prefix = side_prefix or {}
        self.side_env = side_env or {}
        self.side_graphs = side_graphs or {}
        self.log = log
        self.policy = policy
        self.node_log_max_bytes = node_log_max_bytes
        self.user_prefix = list(user_prefix or [])
        self.spec_prefix = spec_prefix or (lambda spec: [])
        self.clock = clock
        self.warm_spares = warm_spares
        self._master_silent_since: Optional[float] = None
        self.running: Dict[str, _Running] = {}
        self.events: List[Event] = []
        self._t0 = time.monotonic()

    def record(self, label, what):
        """Note an event (in the run's log and the report)."""
        self.events.append(Event(time.monotonic() - self._t0, label, what))
        self.log(f"[bringup] {label}: {what}")

    def _graph(self, label):
        return self.side_graphs.get(self.specs_by_label[label].side, self.graph)

    def _topics_by_graph(self):
        return {id(g): set(g.published_topics()) for g in (self.graph, *self.side_graphs.values())}

    def argv_of(self, spec: NodeSpec, node_argv=None):
        """The command that starts `spec` (or `node_argv` in its place: its spare). The CPU budget
        first: `ip netns exec` (a side's prefix with --link) mounts its own /sys, where the cgroup
        folders are not; the groups and the nice value are inherited through it."""
        node_argv = spec.argv if node_argv is None else node_argv
        return [*self.spec_prefix(spec), *self.side_prefix.get(spec.side, []), *self.user_prefix, *node_argv]

    def _start(self, spec: NodeSpec, node_argv=None):
        argv = self.argv_of(spec, node_argv)
        proc = self._graph(spec.label).popen(argv, name=spec.label.replace("/", "_"), env=self.side_env.get(spec.side))
        return proc

    def _restart(self, label, running):
        """The node's new process: its spare, started, if one is ready or still importing and can be
        given the node's priority (its imports run at nice SPARE_NICE: on a saturated side they may never
        finish, a chaos soak's robots' spares did not in a minute); else a new one."""
        spare, running.spare = running.spare, None
        running.spare_due = self.clock() + SPARE_AFTER_UP_S if running.spec.spare and self.warm_spares else None
        if spare is not None and spare.poll() is None and spares.is_waiting_spare(spare.pid):
            ready = spares.is_ready_spare(spare.pid)
            # before it runs: its import thread and what it started get the node's priority
            reniced = spares.take_back_priority(spare.pid)
            if ready or reniced:
                try:
                    os.kill(spare.pid, spares.ACTIVATE_SIGNAL)
                    how = "" if ready else " (still importing: at the node's priority now)"
                    self.record(label, f"restarted from its warm spare{how}")
                    return spare
                except ProcessLookupError:
                    pass  # it died in between: a new process
        if spare is not None:
            stop_all([spare], [SPARE_STOP_TIMEOUT_S])
        return self._start(running.spec)

    def _keep_spares(self):
        """Start the spare of each node that should have one, is up and is due (dead spares too); give
        one still importing after SPARE_PROMOTE_AFTER_S its node's priority."""
        now = self.clock()
        for running in self.running.values():
            if running.spare is not None and running.spare.poll() is not None:
                running.spare = None  # died (killed): another after the delay
                running.spare_due = now + SPARE_AFTER_UP_S
            if running.spare is None and running.up and running.spare_due is not None and now >= running.spare_due:
                running.spare_due = None
                running.spare = self._start(running.spec, spares.spare_argv(running.spec.argv))
                running.spare_promote_at = now + SPARE_PROMOTE_AFTER_S
            if running.spare is not None and running.spare_promote_at is not None and now >= running.spare_promote_at:
                running.spare_promote_at = None
                if not spares.is_ready_spare(running.spare.pid):
                    spares.take_back_priority(running.spare.pid)

    def start_all(self, timeout_s=120.0):
        """Start every spec in dependency order; BringupError names what did not come up."""
        pending = list(self.specs)
        started_at = time.monotonic()
        deadline = started_at + timeout_s
        while True:
            for spec in list(pending):
                if all(self.running.get(dep) and self.running[dep].up for dep in spec.after):
                    self.running[spec.label] = _Running(spec, self._start(spec), waited_s=time.monotonic() - started_at)
                    pending.remove(spec)
            self._refresh_up()
            self._check_deaths(during_start=True)
            if not pending and all(r.up for r in self.running.values()):
                self.record("all", f"{len(self.running)} processes up")
                for running in self.running.values():
                    if running.spec.spare and self.warm_spares:
                        running.spare_due = self.clock() + SPARE_AFTER_UP_S
                return
            if time.monotonic() > deadline:
                missing = [label for label, r in self.running.items() if not r.up] + [s.label for s in pending]
                raise BringupError(self._describe_missing(missing, timeout_s))
            time.sleep(0.25)

    def _describe_missing(self, labels, timeout_s):
        lines = [f"not up after {timeout_s:.0f} s: {', '.join(labels)}"]
        topics_by_graph = self._topics_by_graph()
        for label in labels:
            topics = topics_by_graph[id(self._graph(label))]
            running = self.running.get(label)
            if running is None:
                lines.append(f"  {label}: never started (waits for {', '.join(self.specs_by_label[label].after)})")
                continue
            absent = [t for t in running.spec.wait_topics if t not in topics]
            lines.append(f"  {label}: topics not advertised: {', '.join(absent) or '-'}")
            tail = self._graph(label).output(label.replace("/", "_")).strip().splitlines()[-6:]
            lines.extend(f"    | {line}" for line in tail)
        return "\n".join(lines)

    @property
    def specs_by_label(self):
        return {s.label: s for s in self.specs}

    def _refresh_up(self):
        try:
            topics_by_graph = self._topics_by_graph()
        except OSError:
            return
        for label, running in self.running.items():
            topics = topics_by_graph[id(self._graph(label))]
            alive = running.proc.poll() is None or (running.spec.one_shot and running.proc.returncode == 0)
            if not running.up and alive and all(t in topics for t in running.spec.wait_topics):
                running.up = True

    def _check_deaths(self, during_start=False):
        now = self.clock()
        for label, running in self.running.items():
            if running.restart_at is not None:
                if now >= running.restart_at:
                    running.restart_at = None
                    running.proc = self._restart(label, running)
                    running.up = False
                continue
            code = running.proc.poll()
            if running.ended or code is None or (code == 0 and running.spec.one_shot):
                continue
            if not running.spec.essential:
                running.ended = True
                self.record(label, f"exited with code {code}; not essential: the mission goes on without it")
                continue
            # `nodelet load` and other one-shot helpers exit 0 only when told to; any exit is a death.
            window = self.policy.window_s
            running.restart_times = [t for t in running.restart_times if now - t < window]
            if len(running.restart_times) >= running.spec.restart_limit:
                tail = "\n".join(self._graph(label).output(label.replace("/", "_")).strip().splitlines()[-8:])
                within = f" within {window:.0f} s" if math.isfinite(window) else ""
                raise BringupError(
                    f"{label} exited with code {code} "
                    f"(restarted {len(running.restart_times)} of {running.spec.restart_limit} times)"
                    f"{within}:\n{tail}"
                )
            running.restart_times.append(now)
            running.restarts += 1
            delay_s = self.policy.delay_s(len(running.restart_times))
            self.record(label, restart_note(code, len(running.restart_times), running.spec.restart_limit, delay_s))
            running.restart_at = now + delay_s
            running.up = False

    def _check_master(self):
        code = self.graph.master_exit_code()
        if code is not None:
            raise MasterLost(f"the ROS master exited (code {code})")
        if self.graph.master_online():
            self._master_silent_since = None
            return
        # A master on another host: lost when it has not answered for two polls in a row.
        now = self.clock()
        if self._master_silent_since is None:
            self._master_silent_since = now
        elif now - self._master_silent_since >= 0.5:
            raise MasterLost(f"the ROS master at {self.graph.uri} does not answer")

    def _cap_logs(self):
        """Rotate a node's captured output past `node_log_max_bytes` to <log>.1 (written in append mode,
        so the node goes on writing at the start of the emptied file)."""
        if self.node_log_max_bytes is None:
            return
        for running in self.running.values():
            path = getattr(running.proc, "cps_log", None)
            try:
                if path and os.path.getsize(path) > self.node_log_max_bytes:
                    shutil.copyfile(path, path + ".1")
                    os.truncate(path, 0)
            except OSError:
                continue

    def wait_for_exit(self, timeout_s):
        """Sleep up to `timeout_s` between polls, waking when a node's process ends (its pidfd turns
        readable) or a restart falls due: a death is handled at once, not at the next poll (up to
        0.5 s later, of a kill's recovery; issue 38)."""
        now = self.clock()
        due = [r.restart_at - now for r in self.running.values() if r.restart_at is not None]
        timeout_s = max(0.0, min([timeout_s, *due]))
        fds = []
        try:
            for running in self.running.values():
                if running.restart_at is None and not running.ended and running.proc.poll() is None:
                    with contextlib.suppress(OSError):  # already reaped: the next poll sees it
                        fds.append(os.pidfd_open(running.proc.pid))
            if fds:
                select.select(fds, [], [], timeout_s)
            else:
                time.sleep(timeout_s)
        finally:
            for fd in fds:
                os.close(fd)

    def poll(self):
        """Call periodically: restarts dead processes, raises BringupError past a restart limit and
        MasterLost when the master is gone."""
        self._check_master()
        self._refresh_up()
        self._check_deaths()
        self._keep_spares()
        self._cap_logs()

    def stop(self, label, timeout_s=None):
        """SIGINT `label` (e.g. a node that saves on shutdown) and wait for it, up to `timeout_s`
        (its spec's stop timeout by default); works without a master. True if it exited by itself."""
        running = self.running.get(label)
        if running is None or running.proc.poll() is not None:
            return False
        self.graph.stop(running.proc, timeout_s=running.spec.stop_timeout_s if timeout_s is None else timeout_s)
        return running.proc.returncode is not None and running.proc.returncode >= 0

    def restarts(self):
        return {label: r.restarts for label, r in self.running.items() if r.restarts}

    def stop_all(self):
        """Stop every node at once (SIGINT, each within its own stop timeout, then SIGTERM and
        SIGKILL: cps_ros.processes.stop_all), as Ctrl-C on a terminal would; the masters stay up
        until the caller closes them. One after another, a mission's 17 processes took 8 s."""
        stopping = list(self.running.values())
        waiting = [r.spare for r in stopping if r.spare is not None]
        stop_all(
            [r.proc for r in stopping] + waiting,
            [r.spec.stop_timeout_s for r in stopping] + [SPARE_STOP_TIMEOUT_S] * len(waiting),
        )
        self.running.clear()

    def pid_of(self, label):
        return self.running[label].proc.pid

    def log_of(self, label):
        """The captured output file of `label`'s process (None if it never started)."""
        running = self.running.get(label)
        return getattr(running.proc, "cps_log", None) if running else None


def ensure_port_free(port):
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(("0.0.0.0", port))
        except OSError as exc:
            raise BringupError(f"port {port} is in use ({exc.strerror}); choose another with --port") from exc


def node_log_dir(out_dir):
    path = os.path.join(out_dir, "logs")
    os.makedirs(path, exist_ok=True)
    return path
