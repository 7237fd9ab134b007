"""The reference mission across the real shaped link with the Zenoh transport (cps_bringup's
default): a master per side, each on its own host's loopback, joined only by the two bridges. Every
robot's clouds reach the twin, the link is up, and a command from the twin reaches the robot, which
executes it (its active mode comes back), both ways (teleop, then auto again); from the other host
each host answers at its own bridge listener only."""

import pytest

from cps_harness.reference import ROBOTS, TELEOP_ROBOT
from cps_link import netns_link
from cps_link.bridge_config import load_bridge_table

pytestmark = pytest.mark.skipif(
    netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}"
)


def _listening_ports():
    """Each host's bridge listener: the twin's the main lane's port, the robots' the command lane's."""
    return {netns_link.host_of(side): ports for side, ports in load_bridge_table().listening_ports().items()}


def test_clouds_cross_and_the_link_is_up(reference_mission):
    reference_mission.check()
    observed = reference_mission.observed
    print(f"the readings while the reference mission was up, s: {observed.reading_s}")
    assert not observed.errors, (observed.errors, observed.reading_s)
    # A cloud crossed: the twin's relayed managed topic carries each robot's clouds.
    assert observed.twin_managed_cloud.count("compressed_data:") == len(ROBOTS), observed.twin_managed_cloud
    assert "up: True" in observed.twin_link_state, observed.twin_link_state


def test_a_command_from_the_twin_is_executed_by_the_robot(reference_mission):
    reference_mission.check()
    observed = reference_mission.observed
    assert 'data: "teleop"' in observed.teleop_active, (TELEOP_ROBOT, observed.teleop_active, observed.errors)
    assert 'data: "auto"' in observed.auto_active, (TELEOP_ROBOT, observed.auto_active, observed.errors)


def test_no_ros_port_is_on_the_link_and_the_mission_stopped_by_itself(reference_mission):
    reference_mission.check()
    observed, log = reference_mission.observed, reference_mission.log
    # The twin's master is not reachable at its link address.
    assert observed.twin_master_on_link not in (None, 0), observed.twin_master_on_link
    # One open port per host (issue 38): of every port either host listens on (rosout's and the
    # nodelet manager's XML-RPC servers bind 0.0.0.0), the other reaches its bridge listener only.
    assert observed.open_across_link == _listening_ports(), observed.open_across_link
    assert not reference_mission.mission.killed, "the mission did not stop by itself:\n" + log[-3000:]
    assert "joined by Zenoh bridges" in log and "exited with code" not in log, log[-3000:]
    assert list((reference_mission.out / "logs" / "robots").glob("zenoh_bridge_robots-*.log"))
    assert (reference_mission.out / "map.bt").stat().st_size > 1000
