"""A link cut over real namespaces and the real link: the reference mission's fleet and routes
again, over --transport zenoh, the veth cut for 10 s mid-mission, and the map server killed 2 s into
the cut (fault injection). Both sides report the link down within 1 s of the cut and up within 2 s
of its end; no node but the killed map server restarts, and it resumes from its autosave before the
link comes back; the robots' bridge does not take the cut for a one-way session (no reopen for it); no
live cloud captured more than 1 s before the link came back reaches the twin after it (nothing
waits through the cut: the backfilled keyframes are its only way across); the clouds' latency
after recovery is printed beside the reference mission's (it is the machine's load as much as the
link's: 0.2-0.5 s p95 quiet, up to 1 s with the other worker's tests); the backfilled keyframes
reach the map; and the map's F1 is at least 98 % of the reference mission's (the same mission
without a cut), both printed."""

import re
import sys
import time

import numpy as np
import pytest

from cps_fleet import names
from cps_harness.cut_analysis import (
    LINK_STATE,
    ages_after,
    captured_before,
    count_after,
    describe_ages,
    first_state_after,
    read_watch,
)
from cps_harness.mission import Mission
from cps_harness.reference import ROBOTS
from cps_harness.testing import link_name
from cps_link import netns_link
from cps_ros.processes import find_node
from cps_ros.spare import log_of_waiting_spare

LINK = link_name("zc")

pytestmark = pytest.mark.mission
# The cut, s after every process is up; the map server's kill, s into the mission (bringup's clock
# starts with the mission, just after every process is up): within the cut, after an autosave of
# everything inserted before it (the reference fleet autosaves every 2 s).
CUT_AT_S, CUT_S, KILL_MAP_SERVER_AT_S = 12.0, 10.0, 14.0
DOWN_WITHIN_S, UP_WITHIN_S, FRESH_S, F1_RATIO = 1.0, 2.0, 1.0, 0.98


def _f1(map_file, fleet_file):
    from cps_experiments.report import score_saved_map
    from cps_fleet.fleet import load_fleet

    score, _ = score_saved_map(str(map_file), load_fleet(fleet_file), str(map_file) + ".ground_truth.npz")
    return score.f1


def _live(robot):
    return names.absolute(names.managed_cloud_at_twin(robot))


def _backfill(robot):
    """The keyframes as the twin's bridge delivers them to the map server (still Draco: the map
    server decodes what it inserts, issue 37)."""
    return names.absolute(names.in_twin(names.robot_topic(robot, names.POINTS_BACKFILL_DRACO)))


def _bridge_lines(out):
    """The main lanes' bridges' link up/down and session reopen lines (their node logs)."""
    lines = []
    for log in [
        *(out / "logs").glob("zenoh_bridge_twin-*.log"),
        *(out / "logs" / "robots").glob("zenoh_bridge_robots-*.log"),
    ]:
        lines += [line for line in log.read_text().splitlines() if re.search(r"link (up|down)|reopen", line)]
    return "\n".join(sorted(lines, key=lambda line: line.split("]")[1:2]))


def _reopen_lines(bridge_logs):
    """A main lane's 'reopening the Zenoh session' lines (its node logs; there must be some)."""
    assert bridge_logs, "no bridge log"
    return [line for log in bridge_logs for line in log.read_text().splitlines() if "reopening the Zenoh" in line]


def _reference_latencies(reference_mission):
    """Receive - stamp (s) of the reference mission's live clouds at the twin (its arrivals.csv)."""
    from cps_experiments.run_files import read_rows

    live = {_live(r) for r in ROBOTS}
    rows, _ = read_rows(str(reference_mission.out / "arrivals.csv"))
    return np.array([float(r["receive_s"]) - int(r["stamp_ns"]) / 1e9 for r in rows if r["topic"] in live])


@pytest.mark.skipif(netns_link.capability_problem() is not None, reason=f"{netns_link.capability_problem()}")
@pytest.mark.timeout(900)
def test_a_ten_second_cut_mid_mission(reference_mission, open_tmp_path):
    reference_mission.check()
    out = open_tmp_path / "cut"
    watch = find_node("cps_harness", "link_watch")
    args = ["--fleet", reference_mission.fleet_file, "--kill-map-server-at", KILL_MAP_SERVER_AT_S]
    with Mission(out, args, link="60mbit", link_name=LINK) as mission:
        mission.wait_until_up()
        twin_topics = [t for r in ROBOTS for t in (_live(r), _backfill(r))]
        mission.popen_on("twin", [sys.executable, watch, str(out / "twin_watch.txt"), *twin_topics], "twin_watch")
        mission.popen_on("phys", [sys.executable, watch, str(out / "robots_watch.txt")], "robots_watch")
        time.sleep(CUT_AT_S)
        times = {"cut": time.time()}
        mission.set_link(up=False)
        time.sleep(CUT_S)
        times["restore"] = time.time()
        mission.set_link(up=True)
        mission.finish(timeout_s=600)
    log = mission.log()
    f1_base, f1_cut = (
        _f1(reference_mission.out / "map.bt", reference_mission.fleet_file),
        _f1(out / "map.bt", reference_mission.fleet_file),
    )
    twin, robots = read_watch(out / "twin_watch.txt"), read_watch(out / "robots_watch.txt")
    ages = ages_after(twin, times["restore"], [_live(r) for r in ROBOTS])
    held = captured_before(twin, times["restore"], [_live(r) for r in ROBOTS])
    backfilled = {r: count_after(twin, times["restore"], _backfill(r)) for r in ROBOTS}
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
        f"\nrobots {','.join(ROBOTS)}: F1 without cut (the reference mission) {f1_base:.4f}, with a {CUT_S:.0f} s "
        f"cut and the map server killed in it {f1_cut:.4f} ({100 * f1_cut / f1_base:.1f} %)"
    )
    print("link state delays: " + ", ".join(f"{k} {v:.2f} s" for k, v in delays.items()))
    print("the main lanes' bridges said:\n" + _bridge_lines(out))
    print(
        f"live clouds after recovery: latency {describe_ages(ages)} (the reference mission's, no cut: "
        f"{describe_ages(_reference_latencies(reference_mission))}); captured before the link came back: "
        f"{describe_ages(held[held > 0])}; backfilled keyframes: {backfilled}"
    )

    for key, delay in delays.items():
        assert delay <= (DOWN_WITHIN_S if key.endswith("down") else UP_WITHIN_S), delays
    # The map server, killed, restarted once and resumed from its autosave; no other node restarted.
    assert "map_server: killed by --kill-map-server-at" in log, log[-3000:]
    exits = re.findall(r"\[bringup\] (\S+): exited with code", log)
    assert exits == ["map_server"], (exits, log[-3000:])
    assert re.search(r"map_server: exited with code -?\d+; restart 1/3", log), log[-3000:]
    map_server_logs = sorted(
        (p for p in (out / "logs").glob("map_server-*.log") if not log_of_waiting_spare(p.read_text(errors="replace"))),
        key=lambda p: int(p.stem.split("-")[1]),
    )  # the processes that ran the map server (its warm spares wait in logs of their own)
    assert len(map_server_logs) == 2, map_server_logs
    assert "map_server: resumed from" in map_server_logs[1].read_text()
    # A cut is not a session that carries one way (cps_link bridge.yaml reopen_after_ms): the robots'
    # bridge, which keeps the twin's token through it and hears nothing, does not reopen its session
    # for the twin's silence. (It may after the restore, for the one-way session Zenoh sometimes
    # leaves: the twin heard, its echoes of the robots' heartbeats never coming. That reopen is the
    # cure, printed above with the bridges' lines.) That stall is the twin's deaf one too: the robots'
    # rules fire first, so the twin's main lane never reopens for it (both did once: two outages, one
    # stall); it may for a transport of its own that Zenoh orphaned (cps_link README).
    reopens = _reopen_lines(list((out / "logs" / "robots").glob("zenoh_bridge_robots-*.log")))
    assert not [line for line in reopens if "sent no heartbeat" in line], reopens
    twin_reopens = _reopen_lines(list((out / "logs").glob("zenoh_bridge_twin-*.log")))
    assert not [line for line in twin_reopens if "listed no transport" not in line], twin_reopens
    assert len(held) > 0 and max(held) <= FRESH_S, (
        f"captured up to {max(held, default=float('nan')):.2f} s before the link came back"
    )
    assert all(n > 0 for n in backfilled.values()), backfilled
    assert f1_cut >= F1_RATIO * f1_base, (f1_cut, f1_base)
    assert LINK_STATE in (out / "twin_watch.txt").read_text()
