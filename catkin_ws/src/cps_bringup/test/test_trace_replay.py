"""A trace-driven fleet: the reference mission's recording (3 robots) replayed as 8 robots into the
twin's map server gives 8 distinct robots in the map; a request beyond the hall's placements gets
what fits."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from cps_bringup.supervisor import Supervisor
from cps_bringup.trace_replay import RobotTrace, Trace, TraceError, placements, plan_copies, twin_specs
from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_ros.processes import RosGraph, find_node, free_port, processes_named

REPLAY = find_node("cps_bringup", "trace_replay")
HALL = (-10.0, 10.0, -7.5, 7.5)


def _trace(**extents):
    robots = {
        name: RobotTrace(name, [(0.0, None)], [], [], [], np.array(corners, dtype=float))
        for name, corners in extents.items()
    }
    return Trace(robots, 30.0, "synthetic")


def test_copies_get_their_own_placement_and_time_offset():
    trace = _trace(scout=[(-9.0, -7.0), (-5.0, -3.0)], jackal=[(-9.0, 6.0), (-8.0, 7.0)])
    copies, note = plan_copies(trace, 5, HALL)
    assert note is None and [c.name for c in copies] == ["jackal", "scout", "jackal_c1", "scout_c1", "jackal_c2"]
    assert len({(c.source, c.offset_xy_m) for c in copies}) == 5
    assert copies[0].offset_xy_m == (0.0, 0.0) and copies[2].time_offset_s > 0.0


def test_a_replay_beyond_the_halls_placements_says_so_and_replays_what_fits():
    """A trajectory spanning the hall but 1.5 m each way: 3 x 3 placements 1 m apart (0.3 m from the walls)."""
    wide = [(-8.5, -6.0), (8.5, 6.0)]
    assert len(placements(_trace(a=wide).robots["a"], HALL)) == 9
    copies, note = plan_copies(_trace(a=wide), 20, HALL)
    assert len(copies) == 9 and len({c.offset_xy_m for c in copies}) == 9
    assert "asked for 20 robots" in note and "replaying 9" in note
    with pytest.raises(TraceError):
        plan_copies(_trace(a=wide), 0, HALL)


def _header_msg(frame):
    from sensor_msgs.msg import PointCloud2

    msg = PointCloud2()
    msg.header.frame_id = frame
    return msg


def test_a_robot_played_at_another_rate_keeps_its_clouds_at_their_poses_and_the_replay_counts_its_own_drops():
    """Time scale 0.5: the robot's 4 s trace (clouds at 1, 2, 3, 4 s) plays in 2 s, looping. A publish()
    that raises is the replay's own drop; lateness is measured when publish() has returned."""
    from geometry_msgs.msg import TransformStamped

    from cps_bringup.trace_replay import Copy, Player

    tf = TransformStamped()
    tf.header.frame_id, tf.child_frame_id = names.odom_frame("a"), names.base_frame("a")
    clouds = [(t, _header_msg("a/lidar")) for t in (1.0, 2.0, 3.0, 4.0)]
    trace = Trace(
        {"a": RobotTrace("a", clouds, [], [(t, tf) for t in (0.5, 1.5, 2.5, 3.5)], [], np.zeros((1, 2)))}, 4.0, ""
    )
    now = [0.0]
    sent = []

    def publish_cloud(name, msg):
        now[0] += 0.05  # a publish that blocks 50 ms
        if len(sent) == 1:
            sent.append(None)
            raise OSError("link closed")
        sent.append((name, msg.header.stamp))

    player = Player(
        trace,
        [Copy("a", "a", (0.0, 0.0), 0.0)],
        publish_cloud,
        lambda _transforms: None,
        lambda *_args: None,
        clock=lambda: now[0],
        time_scale={"a": 0.5},
    )
    player._stop.wait = lambda delay: now.__setitem__(0, now[0] + delay) or False
    player.run(2.2, lambda s: s)
    # Due at 0.0 (4 s, looped), 0.5 (raised), 1.0, 1.5 and 2.0 (the loop's second turn).
    assert [stamp for _, stamp in (s for s in sent if s)] == pytest.approx([0.0, 1.0, 1.5, 2.0])
    assert player.sent_clouds == {"a": 4} and player.dropped_clouds == {"a": 1}
    assert player.first_cloud_stamp_s == {"a": pytest.approx(0.0)}  # where its map ages may start counting
    assert player.last_cloud_stamp_s == {"a": pytest.approx(2.0)}  # and where they stop
    assert player.publish_errors == ["a: OSError: link closed"]
    assert player.cloud_lateness_s == pytest.approx([0.05] * 4)


def test_messages_recorded_at_the_same_instant_replay_in_their_recorded_order():
    """final10: the reference bag held two odometry messages of one stamp, and sorting the events
    compared the messages themselves (a TypeError that stopped the replay before its first cloud)."""
    from nav_msgs.msg import Odometry

    from cps_bringup.trace_replay import Copy, Player

    first, second = Odometry(), Odometry()
    first.child_frame_id, second.child_frame_id = "first", "second"
    trace = Trace(
        {
            "a": RobotTrace(
                "a", [(1.0, _header_msg("a/lidar"))], [(1.0, first), (1.0, second)], [], [], np.zeros((1, 2))
            )
        },
        2.0,
        "",
    )
    now = [0.0]
    odometry = []
    player = Player(
        trace,
        [Copy("a", "a", (0.0, 0.0), 0.0)],
        lambda *_args: None,
        lambda _transforms: None,
        lambda _name, msg: odometry.append(msg.child_frame_id),
        clock=lambda: now[0],
    )
    player._stop.wait = lambda delay: now.__setitem__(0, now[0] + delay) or False
    player.run(1.5, lambda s: s)
    assert odometry == ["first", "second"]


COUNT_ROBOTS = """
import json, sys, time, rospy
from cps_fleet import names
from cps_msgs.msg import MapStats
robots = sys.argv[1].split(",")
seen = {}
def on_stats(stats):
    for r in stats.robots:
        seen[r.robot] = (r.clouds_inserted, r.occupied_voxels_contributed)
rospy.init_node("robot_count", anonymous=True)
sub = rospy.Subscriber(names.absolute(names.in_twin(names.MAP_STATS)), MapStats, on_stats)
deadline = time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline and not all(seen.get(r, (0, 0))[1] for r in robots):
    time.sleep(0.2)
print(json.dumps(seen))
"""


def test_recorded_robots_replayed_as_eight_are_eight_robots_in_the_map(reference_mission, open_tmp_path):
    reference_mission.check()
    bag = reference_mission.bag
    recorded = load_fleet(reference_mission.fleet_file)
    assert len(recorded.robots) < 8

    twin_out = open_tmp_path / "twin"
    twin_out.mkdir()
    copies_fleet = str(twin_out / "copies.yaml")
    plan = subprocess.run(
        [sys.executable, REPLAY, bag, "--robots", "8", "--duration", "1", "--copies-fleet", copies_fleet]
        + ["--plan-only"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert plan.returncode == 0, plan.stderr
    copies = load_fleet(copies_fleet).robot_names
    assert len(copies) == 8 and len(set(copies)) == 8

    (twin_out / "logs").mkdir()
    graph = RosGraph(port=free_port(), log_dir=str(twin_out / "logs"))
    supervisor = None
    replay = None
    try:
        graph.start()
        supervisor = Supervisor(twin_specs(copies_fleet, str(twin_out)), graph, log=lambda _m: None)
        supervisor.start_all(timeout_s=120)
        env = dict(os.environ, ROS_MASTER_URI=graph.uri)
        replay = subprocess.Popen(
            [sys.executable, REPLAY, bag, "--robots", "8", "--duration", "40", "--copies-fleet", copies_fleet],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        counted = subprocess.run(
            [sys.executable, "-c", COUNT_ROBOTS, ",".join(copies), "90"],
            env=env,
            capture_output=True,
            text=True,
            timeout=150,
        )
        seen = json.loads(counted.stdout.strip().splitlines()[-1]) if counted.returncode == 0 else counted.stderr
    finally:
        replay_log = ""
        if replay is not None:
            replay.kill()
            replay_log = replay.communicate()[0]
        map_log = _map_server_log(twin_out / "logs")
        if supervisor is not None:
            supervisor.stop_all()
        graph.close()
    assert isinstance(seen, dict), seen
    in_map = sorted(r for r in copies if seen.get(r, (0, 0))[0] > 0 and seen.get(r, (0, 0))[1] > 0)
    assert in_map == sorted(copies), f"{seen}\nthe replay:\n{replay_log[-3000:]}\nthe map server:\n{map_log[-3000:]}"
    assert not processes_named(str(twin_out))


def _map_server_log(folder):
    """The map server's log(s) in the twin's log folder ('' if none)."""
    return "".join(path.read_text(errors="replace") for path in sorted(folder.rglob("map_server*.log")))
