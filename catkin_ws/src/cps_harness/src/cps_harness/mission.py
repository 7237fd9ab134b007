"""The one way a test or a benchmark runs a whole mission: `cps_bringup all` (or the demo, which
runs it and writes its report) in the background, its output in a log file.

    with Mission(out, ["--robots", "jackal", "--duration", "60"], link="60mbit") as mission:
        mission.wait_until_up()
        print(mission.run_on("twin", ["rostopic", "echo", "-n", "1", topic]).stdout)
        mission.finish()          # waits for the end: exit code 0, nothing of it left running

Start, wait for readiness (or any line of its log), read topics and files while it runs (commands
run on either side of the link, against that side's master), cut the link, stop it (Ctrl-C, as a
user would: it saves the map and stops every node) and check that nothing is left behind: no
process naming its folder, none of its link's namespaces. Everything it started is gone when the
context ends, even on failure.
"""

import contextlib
import os
import re
import signal
import subprocess
import sys
import time

from cps_ros.processes import find_node, free_port, processes_named

BRINGUP = ("cps_bringup", "cps_bringup")
DEMO = ("cps_experiments", "demo")

# How long a Ctrl-C'd mission gets to stop by itself before it is killed. Killed, its nodes (each in
# a session of its own) outlive it: test_zenoh_mission found them after a 60 s wait in CI, where the
# mission's orderly stop (every node SIGINT -> SIGTERM -> SIGKILL in turn, the map saved) ran longer.
STOP_TIMEOUT_S = 240.0
POLL_S = 0.05
UP_LINE = "processes up"  # the supervisor's line once every process of the mission is up
PROGRESS_LINE = r"(?m)^\[\s*\d+\.\d s\] "  # the mission's progress, every 10 s of its clock from 0.0

_MASTERS = re.compile(r"\[bringup\] master (http://[\d.]+:(\d+))(?:; robots master (http://[\d.]+:\d+))?")
_LINK = re.compile(r"between namespaces (\w+)_phys")


def program_argv(program, *args):
    """The command line of a mission program (BRINGUP, DEMO) with `args`: for runs that end at once
    (a refusal, --help), whose output a test reads whole."""
    return [sys.executable, find_node(*program), *[str(a) for a in args]]


class MissionEnded(AssertionError):
    """The mission ended before what a test waited for."""


class Mission:
    """A mission run in the background: `program` is BRINGUP (`cps_bringup all ...`) or DEMO.

    `link` (a tc rate such as "60mbit") runs it across a shaped link named `link_name` (a name of
    the caller's, e.g. cps_harness.testing.link_name(tag)); the demo picks its own link (read back
    from its log). `port` is the twin's master port (a free one by default)."""

    def __init__(self, out_dir, args=(), program=BRINGUP, link=None, link_name=None, port=None, log_path=None):
        self.out_dir = str(out_dir)
        self.program = program
        self.port = port or free_port()
        self.link_name = link_name
        self.log_path = log_path or os.path.join(os.path.dirname(self.out_dir), os.path.basename(self.out_dir) + ".log")
        self.argv = program_argv(program, *(["all"] if program == BRINGUP else []))
        self.argv += ["--out", self.out_dir, "--port", str(self.port)]
        if link:
            self.argv += ["--link", link]
        if link_name:
            self.argv += ["--link-name", link_name]
        self.argv += [str(a) for a in args]
        self.proc = None
        self.helpers = []
        self.killed = False  # stop() had to kill the mission: it did not stop within its timeout
        self.seen = {}  # pattern -> monotonic time its first line was seen by a wait
        self.up_at = None

    # --- running ---------------------------------------------------------------------------------
    def start(self):
        os.makedirs(os.path.dirname(self.log_path) or ".", exist_ok=True)
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(
                self.argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True
            )
        self.started_at = time.monotonic()
        return self

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    @property
    def pid(self):
        return self.proc.pid

    def log(self):
        with contextlib.suppress(FileNotFoundError), open(self.log_path, errors="replace") as stream:
            return stream.read()
        return ""

    def running(self):
        return self.proc is not None and self.proc.poll() is None

    def wait_for(self, pattern, timeout_s):
        """The first log line matching the regex `pattern` (a re.Match), waiting up to `timeout_s`;
        `self.seen[pattern]` keeps when a wait first saw it (monotonic, within POLL_S)."""
        deadline = time.monotonic() + timeout_s
        while True:
            match = re.search(pattern, self.log())
            if match:
                self.seen.setdefault(pattern, time.monotonic())
                return match
            if not self.running():
                raise MissionEnded(f"the mission ended ({self.returncode}) before '{pattern}':\n{self.log()[-4000:]}")
            if time.monotonic() >= deadline:
                raise AssertionError(f"no '{pattern}' within {timeout_s} s:\n{self.log()[-4000:]}")
            time.sleep(POLL_S)

    def wait_for_line(self, text, timeout_s):
        return self.wait_for(re.escape(text), timeout_s)

    def wait_until_up(self, timeout_s=300.0):
        """Until the supervisor says every process is up (the robots' clouds have started); then
        `up_at` is when that was seen (monotonic)."""
        match = self.wait_for_line(UP_LINE, timeout_s)
        self.up_at = self.seen[re.escape(UP_LINE)]
        return match

    def wait_until_running(self, timeout_s=60.0):
        """Until the mission's clock runs (its first progress line, once every process is up): a
        Ctrl-C from then on ends the mission (exit 0, the map saved), one before ends its bring-up (130)."""
        return self.wait_for(PROGRESS_LINE, timeout_s)

    def wait_for_masters(self, timeout_s=300.0):
        """Until the mission's master(s) are up (before its nodes start): the match of its log line."""
        return self.wait_for(_MASTERS.pattern, timeout_s)

    @property
    def returncode(self):
        return self.proc.poll() if self.proc else None

    def wait(self, timeout_s):
        """Until the mission ends by itself (its routes done, or --duration); its exit code."""
        return self.proc.wait(timeout_s)

    def finish(self, timeout_s=600.0, expect_code=0):
        """Wait for the mission to end by itself; assert its exit code and that nothing is left."""
        try:
            code = self.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.stop()
            raise AssertionError(f"the mission did not end within {timeout_s} s:\n{self.log()[-4000:]}") from None
        self.stop()
        assert code == expect_code, f"exit code {code}, expected {expect_code}:\n{self.log()[-4000:]}"
        self.assert_nothing_left()
        return self

    def stop(self, timeout_s=STOP_TIMEOUT_S):
        """Ctrl-C the mission (it saves the map and stops everything); kill what is left; remove the link."""
        for helper in self.helpers:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(helper.pid, signal.SIGKILL)
            helper.wait(10)
        self.helpers = []
        if self.proc is None:
            return
        try:
            if self.proc.poll() is None:
                os.killpg(self.proc.pid, signal.SIGINT)
                try:
                    self.proc.wait(timeout_s)
                except subprocess.TimeoutExpired:
                    self.killed = True  # its nodes may outlive it: a test should say so
                    os.killpg(self.proc.pid, signal.SIGKILL)
                    self.proc.wait(10)
        finally:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            link = self.run_link_name()
            if link:
                from cps_link.netns_link import link_down

                link_down(link)

    # --- what it left -------------------------------------------------------------------------------
    def leftovers(self):
        """What of this run still exists: processes naming its folder, its link's namespaces."""
        left = [f"process {pid}: {cmd}" for pid, cmd in processes_named(self.out_dir)]
        link = self.run_link_name()
        if link:
            from cps_link.netns_link import list_namespaces

            left += [f"namespace {ns}" for ns in list_namespaces() if ns.startswith(f"{link}_")]
        return left

    def assert_nothing_left(self):
        left = self.leftovers()
        assert not left, left

    # --- its masters, its link, either side ---------------------------------------------------------
    def _masters(self):
        match = _MASTERS.search(self.log())
        if not match:
            raise AssertionError(f"the mission named no master:\n{self.log()[-2000:]}")
        return match

    def twin_master_uri(self):
        return self._masters().group(1)

    def robots_master_uri(self):
        """The robots' own master (Zenoh transport), or the one master (tcpros)."""
        match = self._masters()
        return match.group(3) or match.group(1)

    def run_link_name(self):
        """The shaped link this run made (given, or as its log names it), None over loopback."""
        if self.link_name:
            return self.link_name
        match = _LINK.search(self.log())
        return match.group(1) if match else None

    def side_argv(self, side, argv):
        """argv run on `side` (phys|twin) against that side's master: in the side's namespace when
        the run has a shaped link."""
        from cps_link.netns_link import namespace, side_ip

        master = self.robots_master_uri() if side == "phys" else self.twin_master_uri()
        link = self.run_link_name()
        zenoh = self._masters().group(3) is not None
        host = re.match(r"http://([\d.]+):", master).group(1)
        env = ["env", f"ROS_MASTER_URI={master}", f"ROS_IP={host if zenoh or not link else side_ip(side)}"]
        prefix = ["ip", "netns", "exec", namespace(link, side)] if link else []
        return [*prefix, *env, *argv]

    def run_on(self, side, argv, timeout_s=30.0):
        """Run argv on one side; the CompletedProcess (text)."""
        return subprocess.run(self.side_argv(side, argv), capture_output=True, text=True, timeout=timeout_s)

    def on_twin(self, argv, timeout_s=30.0):
        return self.run_on("twin", argv, timeout_s)

    def popen_on(self, side, argv, log_name):
        """Start argv on one side in the background (its output in <log_name>.log beside the
        mission's log); stopped with the mission."""
        log = open(os.path.join(os.path.dirname(self.log_path), f"{log_name}.log"), "wb")
        proc = subprocess.Popen(
            self.side_argv(side, argv),
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
        log.close()
        self.helpers.append(proc)
        return proc

    def topic_reader(self, side):
        """A TopicReader on `side` (cps_harness's topic_reader node: one process for every topic
        this test publishes or echoes there); stopped with the mission."""
        log = open(os.path.join(os.path.dirname(self.log_path), f"topic_reader_{side}.log"), "wb")
        proc = subprocess.Popen(
            self.side_argv(side, [sys.executable, find_node("cps_harness", "topic_reader")]),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=log,
            start_new_session=True,
        )
        log.close()
        self.helpers.append(proc)
        return TopicReader(proc)

    def set_link(self, up):
        """Cut (or restore) the link: the physical end of the veth pair down (or up)."""
        from cps_link.netns_link import namespace

        link = self.run_link_name()
        subprocess.run(
            ["ip", "-n", namespace(link, "phys"), "link", "set", f"{link}_p", "up" if up else "down"], check=True
        )


class TopicReader:
    """Requests to a running topic_reader node (its docstring says what they do)."""

    # Beyond a request's own timeout, how long its reply may take (the node's start, under load).
    REPLY_SLACK_S = 60.0

    def __init__(self, proc):
        self.proc = proc

    def _request(self, request, timeout_s):
        import json
        import select

        self.proc.stdin.write((json.dumps(request) + "\n").encode())
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s + self.REPLY_SLACK_S)
        line = self.proc.stdout.readline() if ready else b""
        if not line:
            raise RuntimeError(f"the topic reader gave no reply to {request} (exit code {self.proc.poll()})")
        return json.loads(line)

    def publish(self, topic, data):
        """Latch std_msgs/String `data` on `topic` for the next request (the one that waits for its effect)."""
        self._request({"publish": topic, "data": data}, 0.0)

    def echo(self, topics, timeout_s=30.0, noarr=False, until=None):
        """{topic: one message as `rostopic echo -n 1` prints it ('' if none came)}, all at once;
        with `until`, the first message holding that text."""
        request = {"echo": list(topics), "timeout_s": timeout_s, "noarr": noarr, "until": until}
        return self._request(request, timeout_s)["echo"]


def run_mission(out_dir, args=(), program=BRINGUP, while_up=None, timeout_s=600.0, expect_code=0, **options):
    """Run a mission to its end: `while_up(mission)` (if given) once every process is up, its value
    kept as `mission.read_while_up`. Asserts the exit code and that nothing is left; the Mission."""
    with Mission(out_dir, args, program=program, **options) as mission:
        mission.read_while_up = None
        if while_up is not None:
            mission.wait_until_up()
            mission.read_while_up = while_up(mission)
        mission.finish(timeout_s=timeout_s, expect_code=expect_code)
    return mission
