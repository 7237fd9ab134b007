"""The issue's cut test over real namespaces and the real link: a mission over --transport zenoh,
the veth cut for 10 s mid-mission. Both sides report the link down within 1 s of the cut and up
within 2 s of its end, no node restarts, no live cloud older than 1 s reaches the twin after
recovery, the backfilled keyframes reach the map, and the map's F1 is at least 98 % of the same
mission's without a cut (both printed). CPS_CUT_TEST_ROBOTS picks a subset (default: all four)."""

import os
import subprocess
import sys
import time

import pytest
from cps_experiments.cut_analysis import (
    LINK_STATE,
    ages_after,
    count_after,
    describe_ages,
    first_state_after,
    read_watch,
)
from cps_experiments.mission_run import BackgroundMission

from cps_harness.testing import link_name
from cps_link import netns_link
from cps_ros.processes import processes_named

LINK = link_name("zc")

pytestmark = [pytest.mark.ros, pytest.mark.slow]
HERE = os.path.dirname(os.path.abspath(__file__))
WATCH = os.path.join(HERE, "..", "..", "cps_link", "test", "fixtures", "link_watch.py")
ROBOTS = os.environ.get("CPS_CUT_TEST_ROBOTS", "scout,jackal,champ,iris").split(",")
MISSION_S, CUT_AT_S, CUT_S = 110.0, 35.0, 10.0
DOWN_WITHIN_S, UP_WITHIN_S, FRESH_S, F1_RATIO = 1.0, 2.0, 1.0, 0.98


def _f1(map_file):
    from cps_experiments.report import score_saved_map

    from cps_fleet.fleet import load_fleet, robot_names_arg

    fleet = robot_names_arg(load_fleet(), ROBOTS)
    score, _ = score_saved_map(str(map_file), fleet, str(map_file) + ".ground_truth.npz")
    return score.f1


def _mission(out, cut):
    """One mission; with `cut`, the veth goes down CUT_AT_S into it for CUT_S. Returns (mission, times)."""
    twin_topics = [
        t for r in ROBOTS for t in (f"/twin/{r}/points_filtered/draco/managed", f"/twin/{r}/points_backfill")
    ]
    with BackgroundMission(out, LINK, ["--robots", ",".join(ROBOTS), "--duration", str(MISSION_S)]) as mission:
        mission.wait_for_line("processes up", timeout_s=300)
        mission.popen_on("twin", [sys.executable, WATCH, str(out / "twin_watch.txt"), *twin_topics], "twin_watch")
        mission.popen_on("phys", [sys.executable, WATCH, str(out / "robots_watch.txt")], "robots_watch")
        times = {}
        if cut:
            time.sleep(CUT_AT_S)
            times["cut"] = time.time()
            mission.set_link(up=False)
            time.sleep(CUT_S)
            times["restore"] = time.time()
            mission.set_link(up=True)
        assert mission.wait(timeout_s=MISSION_S + 180) == 0, mission.log()[-4000:]
    return mission, times


@pytest.mark.skipif(netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}")
@pytest.mark.timeout(1500)
def test_a_ten_second_cut_mid_mission(open_tmp_path):
    tmp_path = open_tmp_path  # the nodes run unprivileged: pytest's tmp_path is root-only
    base, _ = _mission(tmp_path / "nocut", cut=False)
    mission, times = _mission(tmp_path / "cut", cut=True)
    f1_base, f1_cut = _f1(tmp_path / "nocut" / "map.bt"), _f1(tmp_path / "cut" / "map.bt")
    twin, robots = read_watch(tmp_path / "cut" / "twin_watch.txt"), read_watch(tmp_path / "cut" / "robots_watch.txt")
    live = [f"/twin/{r}/points_filtered/draco/managed" for r in ROBOTS]
    ages = ages_after(twin, times["restore"], live)
    backfilled = {r: count_after(twin, times["restore"], f"/twin/{r}/points_backfill") for r in ROBOTS}
    delays = {
        f"{side} down": (first_state_after(w, times["cut"], False) or float("inf")) - times["cut"]
        for side, w in (("twin", twin), ("robots", robots))
    }
    delays.update(
        {
            f"{side} up": (first_state_after(w, times["restore"], True) or float("inf")) - times["restore"]
            for side, w in (("twin", twin), ("robots", robots))
        }
    )
    print(
        f"\nrobots {','.join(ROBOTS)}: F1 without cut {f1_base:.4f}, with a {CUT_S:.0f} s cut {f1_cut:.4f} "
        f"({100 * f1_cut / f1_base:.1f} %)"
    )
    print("link state delays: " + ", ".join(f"{k} {v:.2f} s" for k, v in delays.items()))
    print(f"live clouds after recovery: {describe_ages(ages)}; backfilled keyframes: {backfilled}")

    for key, delay in delays.items():
        assert delay <= (DOWN_WITHIN_S if key.endswith("down") else UP_WITHIN_S), delays
    assert "exited with code" not in mission.log() and "exited with code" not in base.log(), mission.log()[-3000:]
    assert len(ages) > 0 and max(ages) <= FRESH_S, describe_ages(ages)
    assert all(n > 0 for n in backfilled.values()), backfilled
    assert f1_cut >= F1_RATIO * f1_base, (f1_cut, f1_base)
    assert not processes_named(str(tmp_path)), processes_named(str(tmp_path))
    assert f"{LINK}_" not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert LINK_STATE in open(tmp_path / "cut" / "twin_watch.txt").read()
