"""The supervisor under faults, on a real master: restart backoff and a windowed limit (clock
injected), a GUI that fails without ending the run, a dead master noticed within 2 s, nodes that
drop root, code they cannot read refused at start, the map kernels they read without compiling,
node output that cannot grow without bound.

The run's master serves every test but the two whose claim is about a master of their own (the
dead master, the killed bringup's roscore); each test's processes are its own and stopped at its end."""

import contextlib
import os
import pwd
import signal
import subprocess
import sys
import time

import pytest

from cps_bringup.plan import DIGITAL, NodeSpec
from cps_bringup.privileges import PrivilegeError, check_code_readable, ensure_map_kernels, hand_over, user_prefix
from cps_bringup.supervisor import BringupError, MasterLost, RestartPolicy, Supervisor
from cps_harness.testing import wait_for
from cps_ros.processes import RosGraph

pytestmark = [pytest.mark.ros, pytest.mark.waiting]

DIES_SOON = "import time; time.sleep(0.3); raise SystemExit(4)"


def _spec(label, code, wait_topics=(), restart_limit=0, essential=True):
    return NodeSpec(
        label,
        DIGITAL,
        (sys.executable, "-c", code),
        wait_topics=tuple(wait_topics),
        restart_limit=restart_limit,
        essential=essential,
    )


class FakeClock:
    def __init__(self):
        self.now_s = 0.0

    def __call__(self):
        return self.now_s


def _poll(supervisor, seconds, period_s=0.1):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        supervisor.poll()
        time.sleep(period_s)


def _next_event(supervisor, events, count, timeout_s=20):
    assert wait_for(lambda: (supervisor.poll(), len(events) >= count)[1], timeout_s), events
    return events[count - 1]


@pytest.fixture
def graph(ros_master, tmp_path):
    """A graph on the run's master (no roscore of its own), its processes' output under tmp_path."""
    with RosGraph(master_uri=ros_master.uri, log_dir=str(tmp_path)) as graph:
        yield graph


def test_restarts_back_off_exponentially_and_the_limit_counts_within_a_window(graph):
    clock, events = FakeClock(), []
    policy = RestartPolicy(backoff_s=1.0, backoff_max_s=4.0, window_s=10.0)
    supervisor = Supervisor(
        [_spec("flaky", DIES_SOON, restart_limit=2)], graph, log=events.append, policy=policy, clock=clock
    )
    try:
        supervisor.start_all(timeout_s=30)
        events.clear()
        assert _next_event(supervisor, events, 1).endswith("restart 1/2 in 1.0 s")
        dead = supervisor.running["flaky"].proc
        _poll(supervisor, 0.5)  # backing off: not restarted yet
        assert supervisor.running["flaky"].proc is dead
        clock.now_s = 1.0
        supervisor.poll()
        assert supervisor.running["flaky"].proc is not dead
        assert _next_event(supervisor, events, 2).endswith("restart 2/2 in 2.0 s")  # doubled
        clock.now_s = 12.0  # both restarts leave the window
        supervisor.poll()
        assert _next_event(supervisor, events, 3).endswith("restart 1/2 in 1.0 s")
        clock.now_s = 13.0
        supervisor.poll()
        assert _next_event(supervisor, events, 4).endswith("restart 2/2 in 2.0 s")
        clock.now_s = 15.0
        supervisor.poll()
        with pytest.raises(BringupError, match=r"restarted 2 of 2 times\) within 10 s"):
            _poll(supervisor, 10.0)
    finally:
        supervisor.stop_all()


def test_a_gui_that_exits_with_an_error_does_not_end_the_mission(graph):
    events = []
    supervisor = Supervisor([_spec("gui", DIES_SOON, essential=False)], graph, log=events.append)
    try:
        supervisor.start_all(timeout_s=30)
        # Polled until its exit is noted (it dies 0.3 s after its start), then a few polls more:
        # none raises, the run goes on.
        assert wait_for(lambda: (supervisor.poll(), any("gui: exited" in e for e in events))[1], 20), events
        _poll(supervisor, 0.5)
    finally:
        supervisor.stop_all()
    assert any("gui: exited with code 4; not essential" in e for e in events), events


def test_a_dead_master_is_noticed_within_2_s(tmp_path):
    with RosGraph(log_dir=str(tmp_path)) as graph:
        supervisor = Supervisor([_spec("sleeper", "import time; time.sleep(600)")], graph, log=lambda *_: None)
        try:
            supervisor.start_all(timeout_s=30)
            supervisor.poll()
            master = next(p for p in graph.processes if p.cps_name == "roscore")
            os.killpg(master.pid, signal.SIGKILL)
            killed_at = time.monotonic()
            with pytest.raises(MasterLost, match="the ROS master exited"):
                while time.monotonic() - killed_at < 10:
                    supervisor.poll()
                    time.sleep(0.5)  # wait_for_mission's period
            noticed_after_s = time.monotonic() - killed_at
            print(f"master loss noticed after {noticed_after_s:.2f} s")
            assert noticed_after_s < 2.0
        finally:
            supervisor.stop_all()


def _uids(pid):
    with open(f"/proc/{pid}/status") as stream:
        line = next(line for line in stream if line.startswith("Uid:"))
    return [int(v) for v in line.split()[1:]]


# Spins as a node does, so SIGINT ends it (rospy's handler swallows the KeyboardInterrupt: a node
# in time.sleep ignored it, and every stop waited out the 3.6 s before SIGTERM).
WRITER = (
    "import os, sys, rospy; from std_msgs.msg import String; rospy.init_node('writer'); "
    "p = rospy.Publisher('/writer/out', String, queue_size=1); "
    "open(os.path.join(sys.argv[1], 'written.csv'), 'w').write('ok'); rospy.spin()"
)


KILLED_PARENT = """
import sys
from cps_bringup.plan import DIGITAL, NodeSpec
from cps_bringup.privileges import user_prefix
from cps_bringup.supervisor import Supervisor
from cps_ros.processes import RosGraph
graph = RosGraph(log_dir=sys.argv[1])
graph.start()
spec = NodeSpec("sleeper", DIGITAL, (sys.executable, "-c", "import time; time.sleep(120)"))
supervisor = Supervisor([spec], graph, log=lambda *_: None, user_prefix=user_prefix("nobody"))
supervisor.start_all(timeout_s=30)
print(graph.processes[0].pid, supervisor.pid_of("sleeper"), flush=True)
sys.stdin.read()
"""


def _gone(pid):
    """Exited: no process, or a zombie nobody has reaped yet."""
    try:
        with open(f"/proc/{pid}/stat") as stream:
            return stream.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping root needs root")
def test_an_unprivileged_node_dies_with_a_killed_supervisor(open_tmp_path):
    """A bringup killed with SIGKILL cleans up nothing: its nodes must go by themselves. setpriv's
    uid change cleared their die-with-parent signal, and a CI run killed that way left the robots'
    nodelet manager running."""
    log_dir = open_tmp_path / "logs"
    hand_over("nobody", str(open_tmp_path), str(log_dir / "log"))
    parent = subprocess.Popen(
        [sys.executable, "-c", KILLED_PARENT, str(log_dir)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    pids = []
    try:
        pids = [int(p) for p in parent.stdout.readline().split()]
        assert len(pids) == 2, "the supervisor did not start its node"
        parent.kill()
        parent.wait()
        assert wait_for(lambda: all(_gone(p) for p in pids), 10), [p for p in pids if not _gone(p)]
    finally:
        parent.kill()
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping root needs root")
def test_nodes_started_as_root_run_unprivileged_and_can_write_the_mission_folder(ros_master, open_tmp_path):
    out = open_tmp_path
    log_dir = out / "logs"
    hand_over("nobody", str(out), str(log_dir / "log"))
    nobody = pwd.getpwnam("nobody").pw_uid
    with RosGraph(master_uri=ros_master.uri, log_dir=str(log_dir)) as graph:
        spec = NodeSpec("writer", DIGITAL, (sys.executable, "-c", WRITER, str(out)), wait_topics=("/writer/out",))
        supervisor = Supervisor([spec], graph, log=lambda *_: None, user_prefix=user_prefix("nobody"))
        try:
            supervisor.start_all(timeout_s=30)
            assert _uids(supervisor.pid_of("writer")) == [nobody] * 4
            assert wait_for(lambda: (out / "written.csv").exists(), 10)
            assert (out / "written.csv").stat().st_uid == nobody
        finally:
            supervisor.stop_all()


def test_a_chatty_node_output_is_rotated_at_its_bound(graph):
    # ~1 MB/s: the bound holds to within what a node writes between two polls.
    chatty = "import time\nwhile True:\n    print('x' * 999, flush=True)\n    time.sleep(0.001)"
    supervisor = Supervisor([_spec("chatty", chatty)], graph, log=lambda *_: None, node_log_max_bytes=100_000)
    rotations = set()  # each rotation copies the log over <log>.1: a new modification time

    def rotated_ten_times():
        supervisor.poll()
        with contextlib.suppress(FileNotFoundError):
            rotations.add(os.stat(log_path + ".1").st_mtime_ns)
        return len(rotations) >= 10

    try:
        supervisor.start_all(timeout_s=30)
        log_path = supervisor.running["chatty"].proc.cps_log
        assert wait_for(rotated_ten_times, 30, poll_s=0.1), f"{len(rotations)} rotations"
        largest = max(os.path.getsize(log_path), os.path.getsize(log_path + ".1"))
    finally:
        supervisor.stop_all()
    assert largest < 3 * 100_000, largest


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping root needs root")
def test_code_closed_to_the_node_user_is_refused_at_start_and_says_so(tmp_path, open_tmp_path):
    """A checkout in a 0700 folder (pytest's tmp_path) was "fleet_sim exited with code 2"; now
    bringup names the file the nodes cannot read before starting anything."""
    closed, readable = tmp_path / "checkout" / "node", open_tmp_path / "node"
    for path in (closed, readable):
        path.parent.mkdir(exist_ok=True)
        path.write_text("print('a node')\n")
        path.chmod(0o755)
    check_code_readable("nobody", [NodeSpec("open", DIGITAL, (sys.executable, str(readable)))])
    with pytest.raises(PrivilegeError) as info:
        check_code_readable(
            "nobody",
            [
                NodeSpec("open", DIGITAL, (sys.executable, str(readable))),
                NodeSpec("closed", DIGITAL, (sys.executable, str(closed))),
            ],
        )
    assert f"'nobody' (not root) but cannot read the code: {closed}" in str(info.value)
    # A file given as a parameter (e.g. fleet_sim's ~video_trace) is checked the same way.
    with pytest.raises(PrivilegeError) as info:
        check_code_readable(
            "nobody", [NodeSpec("sim", DIGITAL, (sys.executable, str(readable), f"_video_trace:={closed}"))]
        )
    assert f"'nobody' (not root) but cannot read an input file: {closed}" in str(info.value)


@pytest.mark.skipif(os.geteuid() != 0, reason="dropping root needs root")
def test_the_unprivileged_nodes_read_the_built_kernels_and_compile_nothing(open_tmp_path):
    """As bringup prepares a mission: the kernels are built (if the set-up has not) where the code
    is, and a process as `nobody`, which cannot write there, loads every one of them."""
    import json

    ensure_map_kernels(log=lambda *_: None)
    code = (
        "import json; from cps_mapping.log_odds_grid import warm_up; w = warm_up(); "
        "print(json.dumps({'compiled': list(w.compiled), 'dir': w.cache_dir}))"
    )
    out = subprocess.run(
        [*user_prefix("nobody"), sys.executable, "-c", code],
        capture_output=True,
        text=True,
        env={**os.environ, "HOME": str(open_tmp_path)},
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["compiled"] == [], result
    nobody = pwd.getpwnam("nobody").pw_uid
    assert all(os.stat(os.path.join(result["dir"], f)).st_uid != nobody for f in os.listdir(result["dir"]))
