"""Eight robots on the shared tissue layout: the tissue runs the same processes on each side as for
the default four, and every robot's clouds reach the map (the map server's per-robot counters)."""
import os
import subprocess
import sys
import time

import pytest
import yaml

from cps_bringup.plan import DIGITAL, PHYSICAL, ZENOH, RunOptions, plan_nodes
from cps_fleet.fleet import load_fleet
from cps_harness.fleets import write_fleet_with_copies
from cps_harness.processes import free_port, processes_named

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")
MISSION_S = 25


def _started(log_dir, robots):
    """The labels of what the supervisor started (one log file per start), without the
    per-robot cps_sim nodes (`<r>_velocity_mux`...) and the masters."""
    labels = [name.rsplit("-", 1)[0] for name in os.listdir(log_dir) if name.endswith(".log")]
    return sorted(label for label in labels if label != "roscore"
                  and not any(label.startswith(f"{r}_") for r in robots))


def _map_stats(port):
    """The map server's per-robot clouds inserted, {robot: n}, or {} when not (yet) published."""
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}")
    try:
        echo = subprocess.run(["rostopic", "echo", "-n", "1", "/twin/map_stats"], env=env, capture_output=True,
                              text=True, timeout=15)
    except subprocess.TimeoutExpired:  # the map server is not up yet
        return {}
    docs = [d for d in yaml.safe_load_all(echo.stdout.replace("\n---", "\n")) if d] if echo.returncode == 0 else []
    return {r["robot"]: r["clouds_inserted"] for r in docs[0]["robots"]} if docs else {}


@pytest.mark.ros
def test_eight_robots_run_on_the_same_tissue_processes_as_four(open_tmp_path):
    fleet_path = write_fleet_with_copies(str(open_tmp_path))
    fleet = load_fleet(fleet_path)
    assert len(fleet.robots) == 8
    out, port = open_tmp_path / "m8", free_port()
    proc = subprocess.Popen([sys.executable, BRINGUP, "all", "--fleet", fleet_path, "--profile", "light",
                             "--duration", str(MISSION_S), "--out", str(out), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    inserted = {}
    try:
        deadline = time.monotonic() + 240
        while proc.poll() is None and time.monotonic() < deadline:
            stats = _map_stats(port)
            inserted.update({r: n for r, n in stats.items() if n})
            if len(inserted) == 8:
                break
            time.sleep(3)
        log = proc.communicate(timeout=240)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, log[-4000:]
    assert sorted(inserted) == sorted(fleet.robot_names), (inserted, log[-3000:])

    four = plan_nodes(load_fleet(), options=RunOptions(out_dir=str(out), transport=ZENOH))
    for side, log_dir in ((PHYSICAL, out / "logs" / "robots"), (DIGITAL, out / "logs")):
        expected = sorted(s.label for s in four if s.side == side and "/" not in s.label)
        assert _started(str(log_dir), fleet.robot_names) == expected, side
    assert not processes_named(str(out))

