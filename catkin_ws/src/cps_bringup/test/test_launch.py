"""Launch files generated for a fleet start with roslaunch: the digital side comes up and the map
topics appear; the <arg>s place the outputs."""

import os
import subprocess
import sys

import pytest

from cps_fleet import names
from cps_ros.processes import RosGraph


@pytest.mark.ros
@pytest.mark.slow
def test_roslaunch_brings_the_digital_side_up(tmp_path):
    launch_dir = tmp_path / "launch"
    result = subprocess.run(
        [sys.executable, "-m", "cps_bringup.launch_xml", "--robots", "jackal", "--out-dir", str(launch_dir)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    text = (launch_dir / "digital.launch").read_text()
    assert '<arg name="fleet_file"' in text and "scout" not in text
    out = tmp_path / "out"
    (tmp_path / "ros").mkdir()
    with RosGraph(log_dir=str(tmp_path / "ros")) as graph:
        launch = graph.popen(["roslaunch", str(launch_dir / "digital.launch"), f"out:={out}"], name="roslaunch")
        try:
            for topic in (
                names.absolute(names.in_twin(names.OCTOMAP_BINARY)),
                names.absolute(names.in_twin(names.POINT_CLOUD_CENTERS)),
                names.absolute(names.in_twin(names.OCCUPIED_CELLS)),
                names.absolute(names.in_twin(names.PROJECTED_MAP)),
                names.absolute(names.in_twin(names.MAP_STATS)),
                names.absolute(names.ALLOCATION),
                names.absolute(names.TISSUE_STATS),
                names.absolute(names.twin_points("jackal")),
            ):
                graph.wait_for_topic(topic, timeout_s=90)
            graph.wait_for_service(
                names.absolute(names.in_twin(names.private(names.MAP_SERVER, names.CLEAR_BBX))), timeout_s=30
            )
        finally:
            graph.stop(launch, timeout_s=20)
    assert (out / "map.bt").exists(), "the map server saves into $(arg out) on shutdown"


def test_generator_refuses_unknown_robots(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "cps_bringup.launch_xml", "--robots", "ghost", "--out-dir", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2 and "unknown robot(s) ghost" in result.stderr
    assert not os.listdir(tmp_path)
