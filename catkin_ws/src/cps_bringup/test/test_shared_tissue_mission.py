"""Eight robots on the shared tissue layout: the tissue runs the same processes on each side as for
the default four, and every robot's clouds reach the map."""

import json
import os
import subprocess
import sys

import pytest

from cps_bringup.plan import DIGITAL, PHYSICAL, ZENOH, RunOptions, plan_nodes
from cps_fleet.fleet import default_fleet_path, load_fleet
from cps_harness.mission import Mission
from cps_ros.spare import log_of_waiting_spare

FLEET8 = os.path.join(os.path.dirname(default_fleet_path()), "fleets", "fleet8.yaml")
# Every robot's clouds must be in the map within this long after every process is up; the mission
# is stopped (Ctrl-C, as a user would) once they are, MISSION_S is only its bound.
COUNT_TIMEOUT_S = 45.0
MISSION_S = 60


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
# /twin/map_stats), printed as a JSON line whenever they change, until every robot has some.
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
printed = None
while printed is None or not all(printed.values()):
    if counts != printed:
        printed = dict(counts)
        print(json.dumps(printed), flush=True)
    time.sleep(0.2)
"""


@pytest.mark.mission
def test_eight_robots_run_on_the_same_tissue_processes_as_four(open_tmp_path):
    """Eight robots (config/fleets/fleet8.yaml) come up with the default four's tissue processes, and
    the map server inserts every robot's clouds."""
    fleet = load_fleet(FLEET8)
    assert len(fleet.robots) == 8

    out = open_tmp_path / "m8"
    args = ["--profile", "light", "--duration", MISSION_S, "--fleet", FLEET8]
    with Mission(out, args) as mission:
        # The counter starts with the twin's master (its Python start beside the bring-up's): it
        # listens from the first cloud on.
        mission.wait_for_masters()
        counter = subprocess.Popen(
            [sys.executable, "-c", COUNT_INSERTED, ",".join(fleet.robot_names)],
            env=dict(os.environ, ROS_MASTER_URI=mission.twin_master_uri()),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            mission.wait_until_up()
            printed, errors = counter.communicate(timeout=COUNT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            counter.kill()
            printed, errors = counter.communicate()
        finally:
            if counter.poll() is None:
                counter.kill()
                counter.wait()
        lines = printed.strip().splitlines()
        counts = json.loads(lines[-1]) if lines else errors[-3000:]
        mission.wait_until_running()
        mission.stop()  # every robot's clouds are in the map (or the wait is over): Ctrl-C
        mission.finish(timeout_s=120)
    assert isinstance(counts, dict) and all(counts.get(r) for r in fleet.robot_names), (counts, mission.log()[-3000:])

    four = plan_nodes(load_fleet(), options=RunOptions(out_dir=str(out), transport=ZENOH))
    for side, log_dir in ((PHYSICAL, out / "logs" / "robots"), (DIGITAL, out / "logs")):
        expected = sorted(s.label for s in four if s.side == side and "/" not in s.label)
        assert _started(str(log_dir), fleet.robot_names) == expected, side
