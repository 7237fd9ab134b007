"""cps_bringup over the real shaped link with --transport zenoh: a master per side, each on its own
host's loopback, joined only by the two bridges. A robot's clouds reach the twin's map, and a
command from the twin reaches the robot, which executes it (its active mode comes back)."""

import subprocess
import time

import pytest
from cps_experiments.mission_run import BackgroundMission

from cps_harness.testing import link_name
from cps_link import netns_link
from cps_ros.processes import processes_named

LINK = link_name("zb")

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.mark.skipif(netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}")
@pytest.mark.timeout(400)
def test_one_robot_mission_over_zenoh(open_tmp_path):
    tmp_path = open_tmp_path  # the nodes run unprivileged: pytest's tmp_path is root-only
    out = tmp_path / "mission"
    with BackgroundMission(out, LINK, ["--robots", "jackal", "--duration", "120"]) as mission:
        mission.wait_for_line("processes up", timeout_s=240)
        # A cloud crossed: the twin's relayed managed topic carries the robot's clouds.
        echo = mission.on_twin(["rostopic", "echo", "-n", "1", "--noarr", "/twin/jackal/points_filtered/draco/managed"])
        assert "compressed_data:" in echo.stdout, echo.stdout + echo.stderr
        link = mission.on_twin(["rostopic", "echo", "-n", "1", "/tissue/link_state"])
        assert "up: True" in link.stdout, link.stdout + link.stderr
        # A command crosses: teleop asked on the twin, the robot's mux reports teleop in force.
        mission.popen_on(
            "twin", ["rostopic", "pub", "-l", "/jackal/control_mode", "std_msgs/String", "teleop"], "control_mode_pub"
        )
        deadline, active = time.monotonic() + 30, ""
        while time.monotonic() < deadline and "teleop" not in active:
            active = mission.on_twin(["rostopic", "echo", "-n", "1", "/jackal/control_mode/active"]).stdout
            time.sleep(1.0)
        assert 'data: "teleop"' in active, active
        # No ROS port of either side is on the link: the twin's master is not reachable at its link address.
        probe = mission.on_twin(
            [
                "python3",
                "-c",
                "import socket; s=socket.socket(); s.settimeout(2); "
                f"print(s.connect_ex(('{netns_link.TWIN_IP}', {mission.port})))",
            ]
        )
        assert probe.stdout.strip() != "0", "the twin's master listens on the link address"
    log = mission.log()
    assert not mission.killed, "the mission did not stop by itself within its timeout:\n" + log[-3000:]
    assert "joined by Zenoh bridges" in log and "exited with code" not in log, log[-3000:]
    assert list((out / "logs" / "robots").glob("zenoh_bridge_robots-*.log"))
    assert (out / "map.bt").exists() and (out / "map.bt").stat().st_size > 1000
    assert not processes_named(str(out)), processes_named(str(out))
    assert f"{LINK}_" not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
