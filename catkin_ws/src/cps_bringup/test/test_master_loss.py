"""roscore killed mid-mission (`cps_bringup all --robots jackal`): noticed within 2 s, the map saved
by the map server's shutdown, everything stopped, exit code 3 (EXIT_MASTER_LOST)."""

import os
import re
import signal
import subprocess
import sys
import threading
import time

import pytest

from cps_bringup.cli import EXIT_MASTER_LOST
from cps_ros.processes import processes_named

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")


class Lines:
    """A process's output lines with their monotonic arrival times."""

    def __init__(self, stream):
        self.lines = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream):
        for line in stream:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def first(self, pattern, timeout_s):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for t, line in list(self.lines):
                if re.search(pattern, line):
                    return t, line
            time.sleep(0.05)
        raise AssertionError(
            f"no line matching {pattern!r} within {timeout_s} s:\n" + "\n".join(line for _, line in self.lines[-40:])
        )


def test_roscore_killed_mid_mission_saves_the_map_and_ends_with_exit_code_3(open_tmp_path):
    out = open_tmp_path / "mission"
    proc = subprocess.Popen(
        [sys.executable, BRINGUP, "all", "--robots", "jackal", "--duration", "300", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    port = None
    try:
        lines = Lines(proc.stdout)
        _, master_line = lines.first(r"\[bringup\] master http://[\d.]+:\d+", 60)
        port = int(re.search(r"master http://[\d.]+:(\d+)", master_line).group(1))
        lines.first(r"processes up", 240)
        lines.first(r"\| map [1-9]\d* voxels", 120)  # the robot drives and the map has begun to fill
        # The master itself (roscore's rosmaster) dies hard; roscore's launcher then ends too.
        master = [pid for pid, cmd in processes_named(f"-p {port}") if "rosmaster" in cmd]
        assert master, processes_named(f"-p {port}")
        os.kill(master[0], signal.SIGKILL)
        killed_at = time.monotonic()
        noticed_at, _ = lines.first(r"roscore: the ROS master (exited|at .* does not answer)", 30)
        assert proc.wait(timeout=120) == EXIT_MASTER_LOST
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    text = "\n".join(line for _, line in lines.lines)
    print(f"master loss noticed after {noticed_at - killed_at:.2f} s")
    assert noticed_at - killed_at < 2.0, noticed_at - killed_at
    assert f"map saved to {out}/map.bt by the map server on shutdown" in text, text[-3000:]
    assert (out / "map.bt").stat().st_size > 0
    assert "the ROS master died; mission ended" in text
    assert not processes_named(f"-p {port}", f"127.0.0.1:{port}")
