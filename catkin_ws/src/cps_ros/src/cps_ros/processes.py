"""A ROS master and the processes started against it, always cleaned up.

    with RosGraph() as graph:
        graph.start_node("cps_transport", "rate_limiter", params={"~rate_hz": 8.0})
        graph.wait_for_topic("/out", timeout_s=10)

Every process is started in its own session with a parent-death signal, so nothing survives its
owner: not on failure, not on Ctrl-C, not when the owner itself is killed. The bringup supervisor
and the test fixtures (`cps_harness.testing`) both build on it.
"""

import contextlib
import ctypes
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

from cps_fleet import names

_PR_SET_PDEATHSIG = 1
# How long stop waits for a killed process group's members to be gone: SIGKILL is not instant on a
# loaded machine (a large process releases its memory first).
GROUP_EXIT_WAIT_S = 5.0


# Listeners' ports are drawn below the kernel's ephemeral range. A port bind(0) hands out is one the
# kernel may also give any outgoing connection between our check and the listener's bind: a loopback
# Zenoh bridge's port, free when chosen, was held by someone else's connection for the 30 s of its
# restarts (final5, 2026-11-28). Below that range only another listener can take it.
LISTEN_PORT_LOW = 20000
EPHEMERAL_RANGE = "/proc/sys/net/ipv4/ip_local_port_range"


def _ephemeral_low():
    try:
        with open(EPHEMERAL_RANGE) as stream:
            return int(stream.read().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768  # Linux's default


def _bindable(port):
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        try:
            sock.bind(("0.0.0.0", port))  # conflicts with a listener on any address
        except OSError:
            return False
    return True


def free_port():
    """A TCP port nobody listens on right now, below the ephemeral range (drawn at random, so that
    parallel test workers do not draw the same one)."""
    high = _ephemeral_low() - 1
    if high > LISTEN_PORT_LOW:
        draw = random.SystemRandom()
        for _ in range(200):
            port = draw.randint(LISTEN_PORT_LOW, high)
            if _bindable(port):
                return port
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as sock:
        sock.bind(("127.0.0.1", 0))  # no room below the ephemeral range: the kernel's pick
        return sock.getsockname()[1]


def _die_with_parent():
    os.setsid()
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)
    except OSError:
        pass


def find_node(package, node):
    """Path of a package's node: `nodes/<node>` of the package rospkg finds (devel space: the
    source tree), else the installed `lib/<package>/<node>` catkin finds (install space)."""
    import rospkg
    from catkin.find_in_workspaces import find_in_workspaces

    path = os.path.join(rospkg.RosPack().get_path(package), "nodes", node)
    if os.path.exists(path):
        return path
    installed = find_in_workspaces(["libexec"], project=package, path=node, first_match_only=True)
    if not installed:
        raise FileNotFoundError(
            f"{package} has no node {node} ({path}, nor in lib/{package} of "
            f"{os.environ.get('CMAKE_PREFIX_PATH', '(no CMAKE_PREFIX_PATH)')})"
        )
    return installed[0]


def stop_all(procs, timeout_s=10.0):
    """SIGINT (as Ctrl-C) to each process group, then SIGTERM to those still running, then SIGKILL;
    each signal to all at once, then waiting for all. `timeout_s`: one for all, or one per process
    (a recorder writing out its buffer gets longer than a node). The groups may hold children that
    outlived their leader (a node's worker processes): killed, and waited for, so that nothing is
    left running when this returns."""
    procs = list(procs)
    timeouts = list(timeout_s) if isinstance(timeout_s, (list, tuple)) else [timeout_s] * len(procs)
    for sig, share in ((signal.SIGINT, 0.6), (signal.SIGTERM, 0.3), (signal.SIGKILL, None)):
        running = [(p, t) for p, t in zip(procs, timeouts) if p.poll() is None]
        if not running:
            break
        for proc, _ in running:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(proc.pid, sig)
        start = time.monotonic()
        for proc, t in running:
            wait_s = 5.0 if share is None else t * share
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(max(0.0, start + wait_s - time.monotonic()))
    for proc in procs:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(proc.pid, signal.SIGKILL)
    deadline = time.monotonic() + GROUP_EXIT_WAIT_S
    while any(group_members(p.pid) for p in procs) and time.monotonic() < deadline:
        time.sleep(0.02)


# Parameters every master we start holds. rospy reads /rosout_disable_topics_generation at every
# log line through its parameter cache, which keeps only a parameter that is set (rospy/msproxy.py,
# get_param_cached): unset, each log line of every node was an XML-RPC call to the master, under
# a lock its shutdown needs too. Four nodes logging fast kept the master so busy that their own
# shutdown's unregister waited behind it for over 10 s (test_shutdown beside busy loops, 5 runs of
# 5). Set to rospy's default.
MASTER_DEFAULTS = {names.ROSOUT_DISABLE_TOPICS_GENERATION: False}


def set_master_defaults(master_uri):
    """Set MASTER_DEFAULTS on the master at `master_uri`."""
    import rosgraph

    master = rosgraph.Master("/cps_master_defaults", master_uri=master_uri)
    for name, value in MASTER_DEFAULTS.items():
        master.setParam(name, value)


def subscribers_of(node, caller_id):
    """{topic: {subscriber node names}} of `node`'s connected publications, from its bus info
    (XML-RPC getBusInfo, which every ROS node serves); empty while the node is not registered."""
    import xmlrpc.client

    import rosgraph

    try:
        uri = rosgraph.Master(caller_id).lookupNode(node)
        _code, _message, connections = xmlrpc.client.ServerProxy(uri).getBusInfo(caller_id)
    except (OSError, rosgraph.MasterError, xmlrpc.client.Error):
        return {}
    out = {}
    for connection in connections:
        _id, destination, direction, _transport, topic, connected = connection[:6]
        if direction == "o" and connected:
            out.setdefault(topic, set()).add(destination)
    return out


class RosGraph:
    """A roscore on a free port plus every process started through it; `close` kills them all."""

    def __init__(self, port=None, log_dir=None, master_uri=None, host_ip="127.0.0.1"):
        self._own_master = master_uri is None
        self.host_ip = host_ip
        self.port = port or (free_port() if self._own_master else int(master_uri.rsplit(":", 1)[1]))
        self.uri = master_uri or f"http://{host_ip}:{self.port}"
        self._own_home = log_dir is None
        self.home = log_dir or tempfile.mkdtemp(prefix="cps-ros-")
        self.processes = []
        self._master = None
        # Nodes started with private parameters: they are removed with the nodes, or a later node
        # of the same name on a shared master would read them.
        self._private_params = set()

    @property
    def env(self):
        env = dict(os.environ)
        env.update(
            ROS_MASTER_URI=self.uri,
            ROS_HOME=self.home,
            ROS_LOG_DIR=os.path.join(self.home, "log"),
            ROS_IP=self.host_ip,
            PYTHONUNBUFFERED="1",
        )
        env.pop("ROS_HOSTNAME", None)
        return env

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.close()

    def attach(self):
        """Another RosGraph on the same master that owns (and kills) only its own processes."""
        return RosGraph(master_uri=self.uri, host_ip=self.host_ip)

    def start(self, timeout_s=30.0):
        if not self._own_master:
            if not self._master_up():
                raise RuntimeError(f"no ROS master at {self.uri}")
            return
        self._master = self.popen(["roscore", "-p", str(self.port)], name="roscore")
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._master.poll() is not None:
                raise RuntimeError(f"roscore exited with {self._master.returncode}: {self.output('roscore')}")
            if self._master_up() and self._has_node(names.ROSOUT):
                set_master_defaults(self.uri)
                return
            time.sleep(0.1)
        self.close()
        raise TimeoutError(f"roscore on port {self.port} did not come up within {timeout_s} s")

    def point_this_process_here(self):
        """Make rospy in this process use this master (rospy reads the environment): call it only in
        a process that has one master for its whole life, e.g. before rospy.init_node."""
        os.environ["ROS_MASTER_URI"] = self.uri
        os.environ["ROS_IP"] = self.host_ip

    def master_exit_code(self):
        """The exit code of this graph's own roscore once it has ended, else None."""
        return self._master.poll() if self._master is not None else None

    def master_online(self):
        try:
            return self._master_up()
        except OSError:
            return False

    def _kill_orphans_of_the_core(self):
        """roslaunch starts rosmaster and rosout in sessions of their own: a roscore killed hard leaves them."""
        for pid, cmd in processes_named(self.uri, f"-p {self.port} "):
            if any(f"/{core} " in cmd or cmd.startswith(core) for core in ("rosmaster", "rosout")):
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, signal.SIGKILL)

    def _master_up(self):
        import rosgraph

        return rosgraph.Master("/cps_test", master_uri=self.uri).is_online()

    def _has_node(self, name):
        import rosgraph

        try:
            state = rosgraph.Master("/cps_test", master_uri=self.uri).getSystemState()
        except Exception:
            return False
        return any(name in nodes for group in state for _, nodes in group)

    def popen(self, argv, name=None, env=None, cwd=None):
        """Start a process against this master; its output goes to a log file under `home`."""
        name = name or os.path.basename(argv[0])
        log_path = os.path.join(self.home, f"{name}-{len(self.processes)}.log")
        log = open(log_path, "ab")  # append: the file may be truncated (rotated) under the process
        merged = self.env
        merged.update(env or {})
        proc = subprocess.Popen(
            argv,
            env=merged,
            cwd=cwd,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            preexec_fn=_die_with_parent,
        )
        proc.cps_name = name
        proc.cps_log = log_path
        log.close()
        self.processes.append(proc)
        return proc

    def start_node(self, package, node, name=None, namespace=None, params=None, remap=None, args=(), env=None):
        """Run `nodes/<node>` of `package` with this venv's python; params are `_name:=value` args."""
        argv = [sys.executable, find_node(package, node), *args]
        if name:
            argv.append(f"__name:={name}")
        if namespace:
            argv.append(f"__ns:={namespace}")
        for key, value in (params or {}).items():
            key = key[1:] if key.startswith("~") else key
            argv.append(f"_{key}:={_param_text(value)}")
        if params:
            self._private_params.add("/".join(["", (namespace or "").strip("/"), name or node]).replace("//", "/"))
        for source, target in (remap or {}).items():
            argv.append(f"{source}:={target}")
        return self.popen(argv, name=name or node, env=env)

    def output(self, name):
        """The captured output of the processes called `name` so far (every one of that name this
        graph started, restarted ones included: `output_of` reads one)."""
        texts = []
        for proc in self.processes:
            if proc.cps_name == name and os.path.exists(proc.cps_log):
                with open(proc.cps_log, "rb") as stream:
                    texts.append(stream.read().decode(errors="replace"))
        return "\n".join(texts)

    @staticmethod
    def output_of(proc):
        """The captured output of the one process `proc` (started by a RosGraph) so far."""
        with open(proc.cps_log, "rb") as stream:
            return stream.read().decode(errors="replace")

    def published_topics(self):
        import rosgraph

        return dict(rosgraph.Master("/cps_test", master_uri=self.uri).getPublishedTopics(""))

    def wait_for_topic(self, topic, timeout_s=20.0):
        """Block until someone advertises `topic`; TimeoutError names what is advertised instead."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if topic in self.published_topics():
                return
            self._raise_if_any_died()
            time.sleep(0.1)
        raise TimeoutError(
            f"{topic} not advertised within {timeout_s} s; advertised: {sorted(self.published_topics())}"
        )

    def wait_for_service(self, service, timeout_s=20.0):
        import rosgraph

        deadline = time.monotonic() + timeout_s
        master = rosgraph.Master("/cps_test", master_uri=self.uri)
        while time.monotonic() < deadline:
            if any(name == service for name, _ in master.getSystemState()[2]):
                return
            self._raise_if_any_died()
            time.sleep(0.1)
        raise TimeoutError(f"service {service} not advertised within {timeout_s} s")

    def _raise_if_any_died(self):
        for proc in self.processes:
            if proc.poll() is not None and proc.returncode != 0 and proc is not self._master:
                raise RuntimeError(
                    f"{proc.cps_name} exited with {proc.returncode}:\n{self.output(proc.cps_name)[-3000:]}"
                )

    def stop(self, proc, timeout_s=10.0):
        """SIGINT (as Ctrl-C), then SIGTERM, then SIGKILL to the process group."""
        stop_all([proc], timeout_s)

    def close(self):
        """Stop every process this graph started, all at once (each takes its own ~1 s to shut
        down: one by one, a module's eight nodes took 9 s), then its master."""
        stop_all([p for p in self.processes if p is not self._master], timeout_s=5.0)
        if self._master in self.processes:
            stop_all([self._master], timeout_s=5.0)
        self.processes = []
        self._forget_private_params()
        if self._own_master:
            self._kill_orphans_of_the_core()
        if self._own_home:
            shutil.rmtree(self.home, ignore_errors=True)

    def _forget_private_params(self):
        import rosgraph

        if self._private_params and not self._own_master:
            master = rosgraph.Master("/cps_harness", master_uri=self.uri)
            for namespace in self._private_params:
                try:
                    if master.hasParam(namespace):
                        master.deleteParam(namespace)
                except Exception:  # a master already gone has nothing left to forget
                    break
        self._private_params = set()


def _param_text(value):
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, dict)):
        import yaml

        return yaml.safe_dump(value, default_flow_style=True).strip()
    return str(value)


def _stat_fields(pid):
    """The fields of /proc/<pid>/stat after the command name (state first), or None once it has gone."""
    try:
        with open(f"/proc/{pid}/stat") as stream:
            return stream.read().rsplit(")", 1)[1].split()
    except OSError:
        return None


def _proc_text(pid, name):
    """/proc/<pid>/<name> (cmdline, environ) with its NULs as spaces, or None once it has gone."""
    try:
        with open(f"/proc/{pid}/{name}", "rb") as stream:
            return stream.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return None


def process_cpu_s(pid, waited_children=False):
    """CPU seconds (user + system) process `pid` has used so far, with `waited_children` also its
    children's that it waited for; 0.0 once it has gone."""
    fields = _stat_fields(pid)
    if fields is None:
        return 0.0
    ticks = sum(int(x) for x in fields[11 : 15 if waited_children else 13])
    return ticks / os.sysconf("SC_CLK_TCK")


def descendants(pid):
    """The pids of every running process below `pid` (its children, theirs...), e.g. a node's
    helper processes, whose CPU `process_cpu_s` counts only once they are waited for."""
    children = {}
    for other in _pids():
        fields = _stat_fields(other)
        if fields is not None:
            children.setdefault(int(fields[1]), []).append(other)
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), ()):
            found.append(child)
            todo.append(child)
    return found


def process_running(pid):
    """True while process `pid` exists and has not ended: a zombie nobody reaped (a killed run's
    bringup whose parent never waits) has ended."""
    fields = _stat_fields(pid)
    return fields is not None and fields[0] not in ("Z", "X")


def process_command(pid, max_chars=120):
    """Process `pid`'s command line, cut to `max_chars`, for a log line; "(gone)" once it has gone."""
    cmd = _proc_text(pid, "cmdline")
    return "(gone)" if cmd is None else cmd.strip()[:max_chars]


def end_processes(pids, grace_s, kill_wait_s=GROUP_EXIT_WAIT_S):
    """SIGTERM `pids`, SIGKILL those still running after `grace_s`, and wait up to `kill_wait_s`
    for them to have ended; the pids still running after that."""
    pids = set(pids)
    for sig, wait_s in ((signal.SIGTERM, grace_s), (signal.SIGKILL, kill_wait_s)):
        for pid in pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, sig)
        deadline = time.monotonic() + wait_s
        while any(process_running(pid) for pid in pids) and time.monotonic() < deadline:
            time.sleep(0.05)
        pids = {pid for pid in pids if process_running(pid)}
        if not pids:
            break
    return pids


def ancestors():
    """This process's pid and its ancestors'."""
    pids, pid = set(), os.getpid()
    while pid > 1 and pid not in pids:
        pids.add(pid)
        fields = _stat_fields(pid)
        if fields is None:
            break
        pid = int(fields[1])
    return pids


def kill_processes_named(needle, wait_s=5.0):
    """SIGKILL every process whose command line or environment mentions `needle` (never this process
    nor its ancestors) and wait up to `wait_s` for them to be gone; the (pid, command) killed."""
    spared = ancestors()
    found = [(pid, cmd) for pid, cmd in processes_named(needle) if pid not in spared]
    for pid, _ in found:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    pids = {pid for pid, _ in found}
    deadline = time.monotonic() + wait_s
    while pids and time.monotonic() < deadline and pids & {pid for pid, _ in processes_named(needle)}:
        time.sleep(0.05)  # zombies are not listed: killed is gone
    return found


def _pids():
    return [int(entry) for entry in os.listdir("/proc") if entry.isdigit()]


def group_members(pgid):
    """The pids of live (not zombie) processes in process group `pgid`."""
    members = []
    for pid in _pids():
        fields = _stat_fields(pid)  # None: it ended meanwhile
        if fields is not None and fields[0] != "Z" and int(fields[2]) == pgid:
            members.append(pid)
    return members


def processes_named(*needles):
    """(pid, command line) of running processes whose command line or environment mentions one of
    `needles`, e.g. a master's port (rosout learns its master only from ROS_MASTER_URI)."""
    found = []
    me = os.getpid()
    for pid in _pids():
        if pid == me:
            continue
        cmd, environ, fields = _proc_text(pid, "cmdline"), _proc_text(pid, "environ"), _stat_fields(pid)
        if cmd is None or environ is None or fields is None or fields[0] == "Z":
            continue
        if any(needle in cmd or needle in environ for needle in needles):
            found.append((pid, cmd.strip()))
    return found
