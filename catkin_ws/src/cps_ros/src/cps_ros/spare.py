"""A warm spare of a Python node: started beside it, imported, waiting; run in its place when it dies.

A node killed mid-mission is back only once a new Python process has imported rospy, numpy, Zenoh
and its own modules: seconds of a loaded CPU's wall time before its first line of work (issue 38's
chaos soak: kills took 3.4-6.3 s against a 3 s bar). The bringup supervisor keeps one spare per
node that asks for it (`NodeSpec.spare`): a process with the node's own argv, placement and
environment that imports what the node imports and then waits for `ACTIVATE_SIGNAL`. A restart is
then that signal: the spare runs the node's script as `__main__`. Android's zygote is the model.
The imports run in a thread at nice `SPARE_NICE`: they take little CPU a node wants (a mission's
start with spares at the nodes' priority once left the map 3.1 s old at 20 s), while the main
thread, which becomes the node, keeps the node's priority.
The spare holds no ROS state (a node calls rospy.init_node in its main), so nothing of it is seen
on the graph until it runs.

    python -m cps_ros.spare NODE_SCRIPT [node args...]

Its command line holds the node's (`__name:=...` included); while it imports its process name
(/proc/<pid>/comm) is `LOADING_COMM`, once ready `SPARE_COMM`, which is how tools that find a node's
process by its command line leave a spare out (`is_waiting_spare`) and how the supervisor tells a
ready one (`is_ready_spare`). A spare started while it still imports waits for its imports (the
start signal is held until then): the supervisor starts it only if it can first give it the node's
priority (`take_back_priority`), else a new process. Once started, its process name is the
script's. SIGTERM or SIGINT while it waits ends it.
"""

import ctypes
import os
import runpy
import signal
import sys
import threading
import time

from cps_ros import priority

ACTIVATE_SIGNAL = signal.SIGUSR2
SPARE_COMM = "cps-spare"
LOADING_COMM = "cps-spare-load"
# CFS weighs nice 10 at 110 against a node's 1024 at nice 0: an import takes about a tenth of a CPU
# beside one busy node. At nice 19 (weight 15) the robots' side of a 4-robot mission left its spares
# importing for minutes: chaos seed 2 (2026-12-01) killed the robots' bridge 20 s after its spare
# had started, still importing; promoted then, it was up 3.1 s after the kill (a ready one: 1.6 s)
# and every map was 4.6-4.8 s old 3 s later.
SPARE_NICE = 10
_PR_SET_NAME = 15
_COMM_BYTES = 15  # the kernel keeps 15 bytes of a process name


def spare_argv(node_argv):
    """The spare's argv for a node run as (python, script, args...)."""
    if len(node_argv) < 2:
        raise ValueError(f"a spare needs (python, script, ...), got {list(node_argv)}")
    return (node_argv[0], "-m", __name__, *node_argv[1:])


_LINE_PREFIX = "[spare] "
_WAITING = ", waiting to be started"
_IMPORTING = ": importing"
_STARTED = ": started"


def importing_line(script):
    """The line a spare prints first, before its imports (at its start, so that its log is a spare's
    from the beginning)."""
    return f"{_LINE_PREFIX}{os.path.basename(script)}{_IMPORTING}"


def waiting_line(script, import_s, import_cpu_s):
    """The line a spare prints once imported, before it waits: how long its imports took, in wall
    time and in CPU time (their wait for a CPU is the difference)."""
    took = f"imported in {import_s:.1f} s ({import_cpu_s:.2f} s of CPU)"
    return f"{_LINE_PREFIX}{os.path.basename(script)}: {took}{_WAITING}"


def started_line(script):
    """The line a spare prints when it is started, before the node's own output."""
    return f"{_LINE_PREFIX}{os.path.basename(script)}{_STARTED}"


def log_of_waiting_spare(text):
    """True if `text`, a process's captured output, is a spare's that was never started, importing
    or waiting (a log file per process: a mission's logs hold its spares' beside its nodes')."""
    lines = [line for line in text.splitlines() if line.startswith(_LINE_PREFIX)]
    return (
        bool(lines) and lines[0].endswith((_IMPORTING, _WAITING)) and not any(line.endswith(_STARTED) for line in lines)
    )


def _comm(pid):
    try:
        with open(f"/proc/{pid}/comm") as stream:
            return stream.read().strip()
    except OSError:
        return None


def is_waiting_spare(pid):
    """True if `pid` is a spare that has not been started, importing or ready (its process name)."""
    return _comm(pid) in (LOADING_COMM, SPARE_COMM)


def is_ready_spare(pid):
    """True if `pid` is a spare done with its imports, waiting to be started."""
    return _comm(pid) == SPARE_COMM


def _set_process_name(name):
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_NAME, os.fsencode(name)[:_COMM_BYTES], 0, 0, 0)
    except (OSError, AttributeError):
        pass  # only the name tools see; the spare works without it


def preload(script):
    """Import what `script` imports at module level, then run its `preload()` if it has one (what
    its main imports late, so that `--help` and a bad argument answer at once, and any warm-up
    that holds no ROS state)."""
    namespace = runpy.run_path(script, run_name="__cps_spare__")
    if callable(namespace.get("preload")):
        namespace["preload"]()


def take_back_priority(pid):
    """Before `pid`, a spare, is started: its threads (an import thread still running) and every
    process it started while importing (the map server's fork server) to the spare's main-thread
    priority, which is the node's, so that neither its rest of the imports nor what they fork for
    the node runs at SPARE_NICE. Needs the right to lower a nice value (the supervisor as root):
    the number of threads set, 0 without it (the node then does without them:
    admission_process.AdmissionClient spawns its receive process). Never raises: a restart goes
    on without it."""
    from cps_ros.processes import descendants

    try:
        nice = priority.process_nice(pid)
        if not priority.may_lower_nice_to(nice):
            return 0
        return sum(priority.renice_process(p, nice) for p in (pid, *descendants(pid)))
    except OSError:  # the spare gone, or not ours to renice
        return 0


def preload_at_low_priority(script):
    """`preload(script)` in a thread at nice SPARE_NICE; its exception, if any, raised here."""
    failed = []

    def run():
        try:
            priority.set_thread_nice(SPARE_NICE)
            preload(script)
        except BaseException as exc:  # noqa: BLE001 - handed to the main thread as it is
            failed.append(exc)

    thread = threading.Thread(target=run, name="spare-preload")
    thread.start()
    thread.join()
    if failed:
        raise failed[0]


def main(argv):
    if not argv:
        print(f"usage: python -m {__name__} NODE_SCRIPT [node args...]", file=sys.stderr)
        return 2
    # blocked before anything else: a start signal sent while the imports run waits for them
    signal.pthread_sigmask(signal.SIG_BLOCK, {ACTIVATE_SIGNAL})
    # Python's own SIGINT handler would only run once sigwait returns: until it is started, Ctrl-C
    # (the supervisor's stop) ends the spare at once. Set before the ready line: a SIGINT sent right
    # after it was once taken by Python's handler and the spare waited on (the suite, final30).
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    _set_process_name(LOADING_COMM)
    script = argv[0]
    print(importing_line(script), flush=True)
    started_s, started_cpu_s = time.monotonic(), time.process_time()
    preload_at_low_priority(script)
    _set_process_name(SPARE_COMM)
    print(waiting_line(script, time.monotonic() - started_s, time.process_time() - started_cpu_s), flush=True)
    signal.sigwait({ACTIVATE_SIGNAL})
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {ACTIVATE_SIGNAL})
    _set_process_name(os.path.basename(script))
    print(started_line(script), flush=True)
    sys.argv = list(argv)
    runpy.run_path(script, run_name="__main__")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
