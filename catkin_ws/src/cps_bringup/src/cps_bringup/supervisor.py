"""Start the planned processes against a master, wait until each is up, restart what dies, stop all.

The supervisor knows processes and topics, nothing of what the nodes do. Up means: the process
runs and every topic in its spec is advertised. A node that does not come up within the timeout
is named in the error, with the end of its log.
"""
import dataclasses
import os
import time
from typing import Dict, List, Optional

from cps_bringup.plan import NodeSpec
from cps_harness.processes import RosGraph


class BringupError(RuntimeError):
    """The system could not be brought up or kept up; the message says what and why."""


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


class Supervisor:
    """Runs `specs` on `graph`'s master. `side_prefix`/`side_env` put a side into a namespace;
    `side_graphs` gives a side its own master (a RosGraph-like object: popen, published_topics,
    output, stop), e.g. the robots' master when the twins are joined by Zenoh bridges."""

    def __init__(self, specs: List[NodeSpec], graph: RosGraph, side_prefix: Optional[Dict[str, List[str]]] = None,
                 side_env: Optional[Dict[str, Dict[str, str]]] = None, log=print,
                 side_graphs: Optional[Dict[str, object]] = None):
        labels = [s.label for s in specs]
        if len(set(labels)) != len(labels):
            raise ValueError(f"duplicate node labels in the plan: {labels}")
        self.specs = specs
        self.graph = graph
        self.side_prefix = side_prefix or {}
        self.side_env = side_env or {}
        self.side_graphs = side_graphs or {}
        self.log = log
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

    def _start(self, spec: NodeSpec):
        argv = [*self.side_prefix.get(spec.side, []), *spec.argv]
        proc = self._graph(spec.label).popen(argv, name=spec.label.replace("/", "_"), env=self.side_env.get(spec.side))
        return proc

    def start_all(self, timeout_s=120.0):
        """Start every spec in dependency order; BringupError names what did not come up."""
        pending = list(self.specs)
        deadline = time.monotonic() + timeout_s
        while True:
            for spec in list(pending):
                if all(self.running.get(dep) and self.running[dep].up for dep in spec.after):
                    self.running[spec.label] = _Running(spec, self._start(spec))
                    pending.remove(spec)
            self._refresh_up()
            self._check_deaths(during_start=True)
            if not pending and all(r.up for r in self.running.values()):
                self.record("all", f"{len(self.running)} processes up")
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
        for label, running in self.running.items():
            code = running.proc.poll()
            if code is None or (code == 0 and running.spec.one_shot):
                continue
            # `nodelet load` and other one-shot helpers exit 0 only when told to; any exit is a death.
            if running.restarts >= running.spec.restart_limit:
                tail = "\n".join(self._graph(label).output(label.replace("/", "_")).strip().splitlines()[-8:])
                raise BringupError(f"{label} exited with code {code} "
                                   f"(restarted {running.restarts} of {running.spec.restart_limit} times):\n{tail}")
            running.restarts += 1
            self.record(label, f"exited with code {code}; restart {running.restarts}/{running.spec.restart_limit}")
            running.proc = self._start(running.spec)
            running.up = False

    def poll(self):
        """Call periodically: restarts dead processes, raises BringupError past a restart limit."""
        self._refresh_up()
        self._check_deaths()

    def restarts(self):
        return {label: r.restarts for label, r in self.running.items() if r.restarts}

    def stop_all(self):
        """Stop in reverse start order (consumers before producers), then the master."""
        for label, running in reversed(list(self.running.items())):
            self._graph(label).stop(running.proc, timeout_s=6.0)
        self.running.clear()

    def pid_of(self, label):
        return self.running[label].proc.pid


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
