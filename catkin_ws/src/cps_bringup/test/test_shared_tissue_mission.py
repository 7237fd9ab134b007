"""Eight robots on the shared tissue layout: the tissue runs the same processes on each side as for
the default four, and every robot's clouds are decoded on the twin."""
import json
import os
import subprocess
import sys
import time

import pytest

from cps_bringup.plan import DIGITAL, PHYSICAL, ZENOH, RunOptions, plan_nodes
from cps_fleet.fleet import load_fleet
from cps_harness.fleets import write_fleet_with_copies
from cps_harness.processes import free_port, processes_named

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")
MISSION_S = 10


def _started(log_dir, robots):
    """The labels of what the supervisor started (one log file per start), without the
    per-robot cps_sim nodes (`<r>_velocity_mux`...) and the masters."""
    labels = [name.rsplit("-", 1)[0] for name in os.listdir(log_dir) if name.endswith(".log")]
    return sorted(label for label in labels if label != "roscore"
                  and not any(label.startswith(f"{r}_") for r in robots))


# Run on the twin's master: counts each robot's decoded clouds until all have some (or 30 s).
COUNT_TWIN_CLOUDS = """
import json, sys, time, rospy
from sensor_msgs.msg import PointCloud2
robots = sys.argv[1].split(",")
counts = dict.fromkeys(robots, 0)
rospy.init_node("twin_cloud_count", anonymous=True)
subs = [rospy.Subscriber(f"/twin/{r}/points", PointCloud2, lambda _m, r=r: counts.__setitem__(r, counts[r] + 1))
        for r in robots]
deadline = time.monotonic() + 30
while time.monotonic() < deadline and not all(counts.values()):
    time.sleep(0.2)
print(json.dumps(counts))
"""


@pytest.mark.ros
@pytest.mark.slow
def test_eight_robots_run_on_the_same_tissue_processes_as_four(open_tmp_path):
    """Eight robots come up with the default four's tissue processes, and every robot's clouds
    are decoded on the twin (/twin/<r>/points, what the map server inserts)."""
    fleet_path = write_fleet_with_copies(str(open_tmp_path))
    fleet = load_fleet(fleet_path)
    assert len(fleet.robots) == 8
    out, port = open_tmp_path / "m8", free_port()
    proc = subprocess.Popen([sys.executable, BRINGUP, "all", "--fleet", fleet_path, "--profile", "light",
                             "--duration", str(MISSION_S), "--out", str(out), "--port", str(port)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    log, counts = [], {}
    try:
        for line in proc.stdout:
            log.append(line)
            if "processes up" in line:
                counted = subprocess.run([sys.executable, "-c", COUNT_TWIN_CLOUDS, ",".join(fleet.robot_names)],
                                         env=dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}"),
                                         capture_output=True, text=True, timeout=60)
                counts = (json.loads(counted.stdout.strip().splitlines()[-1]) if counted.returncode == 0
                          else counted.stderr)
                break
        log += proc.communicate(timeout=120)[0]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    log = "".join(log)
    assert proc.returncode == 0, log[-4000:]
    assert isinstance(counts, dict) and all(counts.get(r) for r in fleet.robot_names), (counts, log[-3000:])

    four = plan_nodes(load_fleet(), options=RunOptions(out_dir=str(out), transport=ZENOH))
    for side, log_dir in ((PHYSICAL, out / "logs" / "robots"), (DIGITAL, out / "logs")):
        expected = sorted(s.label for s in four if s.side == side and "/" not in s.label)
        assert _started(str(log_dir), fleet.robot_names) == expected, side
    assert not processes_named(str(out))
