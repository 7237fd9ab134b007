"""cps_ros.spare: a node's warm spare imports ahead, waits without being the node, and runs the node's
script as __main__ with the node's arguments when started; Ctrl-C ends a waiting spare at once."""

import contextlib
import os
import re
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from cps_harness.testing import Gate
from cps_ros import spare

pytestmark = pytest.mark.unit

NODE = textwrap.dedent("""
    import os, sys
    print("top level", flush=True)

    def preload():
        print("preloaded", flush=True)
        print("nice", os.getpriority(os.PRIO_PROCESS, 0), os.getpriority(os.PRIO_PROCESS, os.getpid()), flush=True)

    def main():
        print("main", os.path.basename(sys.argv[0]), *sys.argv[1:], flush=True)
        print("nice", os.getpriority(os.PRIO_PROCESS, 0), flush=True)
        return int(sys.argv[1])

    if __name__ == "__main__":
        sys.exit(main())
""")


def _spare_of(tmp_path, text):
    """A spare of a node script with `text`, its output piped."""
    script = tmp_path / "node"
    script.write_text(text)
    return subprocess.Popen(list(spare.spare_argv((sys.executable, str(script)))), stdout=subprocess.PIPE, text=True)


def _spare(tmp_path, *args):
    script = tmp_path / "node"
    script.write_text(NODE)
    proc = subprocess.Popen(
        list(spare.spare_argv((sys.executable, str(script), *args))), stdout=subprocess.PIPE, text=True
    )
    lines = [proc.stdout.readline() for _ in range(5)]
    return proc, lines


def test_a_spare_preloads_once_waits_and_runs_the_node_with_its_arguments(tmp_path):
    proc, lines = _spare(tmp_path, "3", "__name:=spared")
    try:
        # imported at SPARE_NICE in a thread of its own; the main thread, the node to be, at 0
        assert lines[:4] == ["[spare] node: importing\n", "top level\n", "preloaded\n", f"nice {spare.SPARE_NICE} 0\n"]
        assert re.fullmatch(
            r"\[spare\] node: imported in \d+\.\d s \(\d+\.\d\d s of CPU\), waiting to be started\n", lines[4]
        )
        assert spare.log_of_waiting_spare("".join(lines)) and spare.log_of_waiting_spare(lines[0])
        assert proc.poll() is None and spare.is_waiting_spare(proc.pid) and spare.is_ready_spare(proc.pid)
        os.kill(proc.pid, spare.ACTIVATE_SIGNAL)
        out, _ = proc.communicate(timeout=30)
    finally:
        proc.kill()
    # the script's top level again (imports cached), main with the node's own argv at the node's
    # priority; its exit code
    assert out.splitlines() == ["[spare] node: started", "top level", "main node 3 __name:=spared", "nice 0"]
    assert not spare.log_of_waiting_spare("".join(lines) + out)  # a started spare's log is its node's
    assert proc.returncode == 3


def test_a_started_spare_is_named_after_its_node(tmp_path):
    script = tmp_path / "node"
    script.write_text("import time\nif __name__ == '__main__':\n    print('up', flush=True); time.sleep(30)\n")
    proc = subprocess.Popen(list(spare.spare_argv((sys.executable, str(script)))), stdout=subprocess.PIPE, text=True)
    try:
        proc.stdout.readline()
        proc.stdout.readline()
        os.kill(proc.pid, spare.ACTIVATE_SIGNAL)
        assert proc.stdout.readline() == "[spare] node: started\n" and proc.stdout.readline() == "up\n"
        assert not spare.is_waiting_spare(proc.pid)
        with open(f"/proc/{proc.pid}/comm") as stream:
            assert stream.read().strip() == "node"
    finally:
        proc.kill()
        proc.wait()


def test_ctrl_c_ends_a_waiting_spare_at_once(tmp_path):
    proc, _ = _spare(tmp_path, "0")
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=5) == -signal.SIGINT and time.monotonic() - t0 < 2.0


def test_a_spare_needs_a_script():
    with pytest.raises(ValueError, match="a spare needs"):
        spare.spare_argv((sys.executable,))
    result = subprocess.run([sys.executable, "-m", "cps_ros.spare"], capture_output=True, text=True)
    assert result.returncode == 2 and "usage" in result.stderr


def test_a_spare_started_while_importing_finishes_at_the_nodes_priority_then_runs_the_node(tmp_path):
    """On a saturated side a spare's imports at SPARE_NICE may not finish (a chaos soak's robots'
    spares did not in a minute): the supervisor, as root, gives it the node's priority and starts
    it; the start waits for the imports, then the node runs."""
    go = Gate(tmp_path / "imports_may_finish")
    proc = _spare_of(
        tmp_path,
        "import os, sys\n"
        "def preload():\n"
        "    print('loading', flush=True)\n"
        f"    open({go.path!r}).close()\n"
        "    print('imports done at nice', os.getpriority(os.PRIO_PROCESS, 0), flush=True)\n"
        "if __name__ == '__main__':\n"
        "    print('node at nice', os.getpriority(os.PRIO_PROCESS, 0), flush=True)\n",
    )
    try:
        assert proc.stdout.readline() == "[spare] node: importing\n" and proc.stdout.readline() == "loading\n"
        assert spare.is_waiting_spare(proc.pid) and not spare.is_ready_spare(proc.pid)
        assert spare.take_back_priority(proc.pid) >= 2  # its main and import threads (root here)
        os.kill(proc.pid, spare.ACTIVATE_SIGNAL)
        go.release()
        out, _ = proc.communicate(timeout=30)
    finally:
        proc.kill()
        proc.wait()
        go.close()
    lines = out.splitlines()
    assert lines[0] == "imports done at nice 0" and lines[2:] == ["[spare] node: started", "node at nice 0"]
    assert lines[1].startswith("[spare] node: imported in ") and lines[1].endswith(", waiting to be started")


def test_a_preload_that_fails_ends_the_spare_with_its_error(tmp_path):
    script = tmp_path / "node"
    script.write_text("def preload():\n    raise RuntimeError('no kernels')\n")
    result = subprocess.run(
        list(spare.spare_argv((sys.executable, str(script)))), capture_output=True, text=True, timeout=30
    )
    assert result.returncode != 0 and "RuntimeError: no kernels" in result.stderr
    assert "waiting to be started" not in result.stdout


def test_what_a_spare_started_while_importing_takes_the_node_priority_back(tmp_path):
    """The map server's spare starts a fork server from its import thread (SPARE_NICE); before it starts
    the spare, the supervisor sets such processes back to the spare's main-thread priority."""
    proc = _spare_of(
        tmp_path,
        "import subprocess\n"
        "def preload():\n"
        "    global helper\n"
        "    helper = subprocess.Popen(['sleep', '60'])\n"
        "    print('helper', helper.pid, flush=True)\n",
    )
    helper = None
    try:
        assert proc.stdout.readline() == "[spare] node: importing\n"
        helper = int(proc.stdout.readline().split()[1])
        assert "waiting" in proc.stdout.readline()
        assert os.getpriority(os.PRIO_PROCESS, helper) == spare.SPARE_NICE
        assert spare.take_back_priority(proc.pid) >= 1  # run as root here
        assert os.getpriority(os.PRIO_PROCESS, helper) == os.getpriority(os.PRIO_PROCESS, proc.pid) == 0
        os.kill(proc.pid, spare.ACTIVATE_SIGNAL)
        assert spare.take_back_priority(2**22 + 1) == 0  # no such process: nothing, no error
    finally:
        proc.kill()
        proc.wait()
        if helper is not None:  # its own helper only, not any `sleep 60` on the machine
            with contextlib.suppress(ProcessLookupError):
                os.kill(helper, signal.SIGKILL)


def test_a_log_is_a_waiting_spares_from_its_first_line_until_it_is_started():
    assert spare.log_of_waiting_spare(spare.importing_line("/x/map_server") + "\n")  # still importing
    assert spare.log_of_waiting_spare("[spare] map_server: importing\nkernels loaded\n")
    assert not spare.log_of_waiting_spare("[spare] map_server: importing\n[spare] map_server: started\nup\n")
    assert not spare.log_of_waiting_spare("")  # nothing printed: not known to be a spare
    assert not spare.log_of_waiting_spare("[INFO] map_server: resumed from map.bt\n")
