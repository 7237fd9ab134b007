"""roscore killed mid-mission (`cps_bringup all --robots jackal`): noticed within 2 s, the map saved
by the map server's shutdown, everything stopped, exit code 3 (EXIT_MASTER_LOST)."""

import os
import signal
import time

import pytest

from cps_bringup.cli import EXIT_MASTER_LOST
from cps_harness.mission import Mission
from cps_ros.processes import processes_named

pytestmark = pytest.mark.mission


def _wait_for_first_insertion(map_age_csv, robot, mission, timeout_s):
    """Until the map server says it inserted a cloud of `robot` (its map_stats, as the mission's
    map_age.csv logs each one, flushed row by row): at once, where the mission's progress line,
    printed every 10 s, says so 10 s into the mission."""
    import csv

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if map_age_csv.exists():
            with open(map_age_csv, newline="") as stream:
                if any(
                    row["robot"] == robot and int(row["clouds_inserted"] or 0) > 0 for row in csv.DictReader(stream)
                ):
                    return
        assert mission.running(), mission.log()[-3000:]
        time.sleep(0.2)
    raise AssertionError(f"no cloud of {robot} inserted within {timeout_s} s:\n{mission.log()[-3000:]}")


def test_roscore_killed_mid_mission_saves_the_map_and_ends_with_exit_code_3(open_tmp_path):
    out = open_tmp_path / "mission"
    with Mission(out, ["--robots", "jackal", "--duration", "300"]) as mission:
        mission.wait_until_up(240)
        _wait_for_first_insertion(out / "map_age.csv", "jackal", mission, 120)  # the map has begun to fill
        # The master itself (roscore's rosmaster) dies hard; roscore's launcher then ends too.
        master = [pid for pid, cmd in processes_named(f"-p {mission.port}") if "rosmaster" in cmd]
        assert master, processes_named(f"-p {mission.port}")
        os.kill(master[0], signal.SIGKILL)
        killed_at = time.monotonic()
        noticed = r"roscore: the ROS master (exited|at .* does not answer)"
        mission.wait_for(noticed, 30)
        noticed_at = mission.seen[noticed]
        mission.finish(timeout_s=120, expect_code=EXIT_MASTER_LOST)
    text = mission.log()
    print(f"master loss noticed after {noticed_at - killed_at:.2f} s (read every {0.05} s)")
    assert noticed_at - killed_at < 2.0, noticed_at - killed_at
    assert f"map saved to {out}/map.bt by the map server on shutdown" in text, text[-3000:]
    assert (out / "map.bt").stat().st_size > 0
    assert "the ROS master died; mission ended" in text
    assert not processes_named(f"-p {mission.port}", f"127.0.0.1:{mission.port}")
