"""Eight robots on the shared tissue layout: the tissue runs the same processes on each side as for
the default four, and every robot's clouds reach the map."""

import json
import os
import subprocess
import sys

import pytest

from cps_bringup.plan import DIGITAL, PHYSICAL, ZENOH, RunOptions, plan_nodes
from cps_fleet.fleet import default_fleet_path, load_fleet
from cps_harness.mission import run_mission
from cps_ros.spare import log_of_waiting_spare

FLEET8 = os.path.join(os.path.dirname(default_fleet_path()), "fleets", "fleet8.yaml")
MISSION_S = 15


def _started(log_dir, robots):
    """The labels of what the supervisor started (one log file per start), without the
    per-robot cps_sim nodes (`<r>_velocity_mux`...), the masters and the warm spares still waiting."""
    labels = [
        name.rsplit("-", 1)[0]
        for name in os.listdir(log_dir)
        if name.endswith(".log") and not log_of_waiting_spare(_read(os.path.join(log_dir, name)))
    ]
    return sorted(
        label for label in labels if label != "roscore" and not any(label.startswith(f"{r}_") for r in robots)
    )


def _read(path):
    with open(path, errors="replace") as stream:
        return stream.read()


# Run on the twin's master: each robot's clouds inserted into the map (the map server's
# /twin/map_stats) until every robot has some (or 45 s).
COUNT_INSERTED = """
import json, sys, time, rospy
from cps_fleet import names
from cps_msgs.msg import MapStats
robots = sys.argv[1].split(",")
counts = dict.fromkeys(robots, 0)
def on_stats(stats):
    for robot in stats.robots:
        if robot.robot in counts:
            counts[robot.robot] = robot.clouds_inserted
rospy.init_node("map_insert_count", anonymous=True)
sub = rospy.Subscriber(names.absolute(names.in_twin(names.MAP_STATS)), MapStats, on_stats)
deadline = time.monotonic() + 45
while time.monotonic() < deadline and not all(counts.values()):
    time.sleep(0.2)
print(json.dumps(counts))
"""


@pytest.mark.mission
def test_eight_robots_run_on_the_same_tissue_processes_as_four(open_tmp_path):
    """Eight robots (config/fleets/fleet8.yaml) come up with the default four's tissue processes, and
    the map server inserts every robot's clouds."""
    fleet = load_fleet(FLEET8)
    assert len(fleet.robots) == 8

    def count_inserted(mission):
        counted = subprocess.run(
            [sys.executable, "-c", COUNT_INSERTED, ",".join(fleet.robot_names)],
            env=dict(os.environ, ROS_MASTER_URI=mission.twin_master_uri()),
            capture_output=True,
            text=True,
            timeout=60,
        )
        return json.loads(counted.stdout.strip().splitlines()[-1]) if counted.returncode == 0 else counted.stderr

    out = open_tmp_path / "m8"
    args = ["--profile", "light", "--duration", MISSION_S, "--fleet", FLEET8]
    mission = run_mission(out, args, while_up=count_inserted, timeout_s=120)
    counts = mission.read_while_up
    assert isinstance(counts, dict) and all(counts.get(r) for r in fleet.robot_names), (counts, mission.log()[-3000:])

    four = plan_nodes(load_fleet(), options=RunOptions(out_dir=str(out), transport=ZENOH))
    for side, log_dir in ((PHYSICAL, out / "logs" / "robots"), (DIGITAL, out / "logs")):
        expected = sorted(s.label for s in four if s.side == side and "/" not in s.label)
        assert _started(str(log_dir), fleet.robot_names) == expected, side
