"""Fixtures of cps_bringup's tests (the workspace's ros_master/ros/rospy_node come from the top conftest)."""

import dataclasses
import os
import pathlib
import subprocess
import sys

import pytest

from cps_ros.processes import free_port, processes_named

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")


@dataclasses.dataclass
class Mission:
    """A `cps_bringup all` run: its folder, master port and pid, and once it ended its output and
    what the test read while every process was up."""

    out: pathlib.Path
    port: int
    pid: int = 0
    log: str = ""
    read_while_up: object = None


@pytest.fixture
def bringup_mission(open_tmp_path):
    """Returns run(name, args, read_while_up, duration_s): runs `cps_bringup all --profile light`
    for `duration_s` on a free port into `<open tmp>/<name>` with `args`, calls
    `read_while_up(mission)` once the supervisor says every process is up, and returns the Mission
    after checking that the run ended with 0 and left no process behind."""

    def run(name, args, read_while_up, duration_s, timeout_s=180):
        mission = Mission(out=open_tmp_path / name, port=free_port())
        argv = [sys.executable, BRINGUP, "all", "--profile", "light", "--duration", str(duration_s)]
        argv += ["--out", str(mission.out), "--port", str(mission.port), *args]
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        mission.pid = proc.pid
        log = []
        try:
            for line in proc.stdout:
                log.append(line)
                if "processes up" in line:
                    mission.read_while_up = read_while_up(mission)
                    break
            log += proc.communicate(timeout=timeout_s)[0]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        mission.log = "".join(log)
        assert proc.returncode == 0, mission.log[-4000:]
        assert not processes_named(str(mission.out))
        return mission

    return run
