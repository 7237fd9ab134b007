"""Admission before work (issue 37), without a master: a cloud is held as it arrived and costs
nothing until the insertion takes it (a superseded one is never deserialized nor decoded), robots
are served oldest map first, a cloud whose transform is late waits in its slot instead of blocking
the insertion, keyframes after an outage wait in their own FIFO, and every cloud ends in exactly one
counter (the ledger balances, gaps in the senders' sequence numbers included)."""

import io
import logging

import genpy
import pytest
import rospy
import test_map_server_library as library
from test_map_server_library import JACKAL_FRAME, JACKAL_POSE, _cloud, _server, drain

from cps_fleet import names
from cps_mapping.admission import Admission
from cps_mapping.map_server import TransformUnavailable
from cps_mapping.queues import Arrival, RobotSlots
from cps_ros import spare
from cps_transport.draco import DracoEncoder


@pytest.fixture(scope="module")
def jackal_points():
    return library.jackal_points.__wrapped__()


class CountingDecoder:
    """The server's Draco decoder, counting its calls."""

    def __init__(self, decoder):
        self.decoder, self.calls = decoder, 0

    def decode(self, msg):
        self.calls += 1
        return self.decoder.decode(msg)


def _compressed(points, secs, seq=0, frame=JACKAL_FRAME):
    msg = DracoEncoder(leaf_size_m=0.1).encode(_cloud(points, frame=frame))
    msg.header.stamp, msg.header.seq = genpy.Time(secs, 0), seq
    return msg


def _as_received(msg, publisher="/replay"):
    """What a rospy.AnyMsg subscriber hands over: the serialized bytes and the connection header."""
    buffer = io.BytesIO()
    msg.serialize(buffer)
    raw = rospy.AnyMsg().deserialize(buffer.getvalue())
    raw._connection_header = {"type": msg._type, "callerid": publisher}
    return raw


def test_a_superseded_cloud_is_never_decoded(jackal_points):
    server, _ = _server(robots=("jackal",))
    server.decoder = counting = CountingDecoder(server.decoder)
    for secs in range(100, 110):
        server.receive_cloud("jackal", _as_received(_compressed(jackal_points, secs, seq=secs)))
    c = server.robot_counters("jackal")
    assert (c.clouds_received, c.clouds_superseded, counting.calls) == (10, 9, 0), "admission decodes nothing"
    assert server.waiting("jackal") == 1
    assert server.insert_pending(timeout_s=0) == 1
    c = server.robot_counters("jackal")
    assert counting.calls == 1 and c.clouds_inserted == 1 and c.newest_inserted_stamp_s == 109.0


def test_the_robot_whose_map_is_oldest_is_served_first(jackal_points):
    slots = RobotSlots(["a", "b", "c"], clock=lambda: 0.0)
    slots.served("a", 50.0)
    slots.served("b", 10.0)  # b's map is the oldest that has one; c has none at all
    for robot in ("a", "b", "c"):
        slots.put(Arrival(robot, None, arrived_s={"a": 1.0, "b": 2.0, "c": 3.0}[robot]))
    assert [slots.take(timeout_s=0).robot for _ in range(3)] == ["c", "b", "a"]
    # Under overload every robot is served in turn: after an insertion its map is the freshest.
    order = []
    for step in range(6):
        for robot in ("a", "b", "c"):
            slots.put(Arrival(robot, None, arrived_s=float(step)))
        taken = slots.take(timeout_s=0)
        slots.served(taken.robot, 100.0 + step)
        order.append(taken.robot)
    assert sorted(order[:3]) == ["a", "b", "c"] and order[3:] == order[:3]


def test_a_cloud_whose_transform_is_late_waits_in_its_slot_and_the_insertion_serves_others(jackal_points):
    known = {JACKAL_FRAME: False}

    def transform_of(frame, _stamp):
        if not known.get(frame):
            raise TransformUnavailable(f"{frame} not yet")
        return JACKAL_POSE[1], JACKAL_POSE[0]

    server, _ = _server(robots=("jackal", "scout"), tf_timeout_s=5.0)
    server.admission.transform_of = transform_of
    server.receive_cloud("jackal", _cloud(jackal_points))
    assert server.insert_pending(timeout_s=0) == 0 and server.waiting("jackal") == 1, "deferred, not dropped"
    assert server.insert_pending(timeout_s=0) == 0, "not ready again at once: no busy loop"
    known[JACKAL_FRAME] = True
    assert server.insert_pending(timeout_s=1.0) == 1
    c = server.robot_counters("jackal")
    assert (c.clouds_inserted, c.clouds_dropped_tf, c.clouds_superseded) == (1, 0, 0)
    # A newer cloud that arrives while the older one waits for its transform waits beside it (a
    # third supersedes the newer); the older one goes first once its transform is known.
    known[JACKAL_FRAME] = False
    server.receive_cloud("jackal", _cloud(jackal_points))
    server.insert_pending(timeout_s=0)
    server.receive_cloud("jackal", _cloud(jackal_points))
    assert server.robot_counters("jackal").clouds_superseded == 0 and server.waiting("jackal") == 2
    server.receive_cloud("jackal", _cloud(jackal_points))
    assert server.robot_counters("jackal").clouds_superseded == 1 and server.waiting("jackal") == 2
    known[JACKAL_FRAME] = True
    assert drain(server) == 2
    c = server.robot_counters("jackal")
    assert (c.clouds_inserted, c.clouds_superseded, c.clouds_dropped_tf) == (3, 1, 0)


def test_clouds_keep_going_in_while_a_robots_transforms_lag_behind_its_clouds(jackal_points):
    """Live (a demo, 52-55 s): the robots' tf reached the twin 0.3-0.6 s after its stamps, the clouds
    0.1-0.3 s after theirs; each cloud waiting for its transform was superseded by the next before
    the transform came, and three robots' maps stood still for 3 s. Here every transform is known
    0.5 s after its stamp and a cloud arrives every 0.1 s: the insertion takes one whenever it can."""
    now = [100.0]

    def transform_of(_frame, stamp):
        if stamp.to_sec() > now[0] - 0.5:
            raise TransformUnavailable("tf not there yet")
        return JACKAL_POSE[1], JACKAL_POSE[0]

    admission = Admission(
        ["jackal"], transform_of, 2.0, names.MAP_FRAME, logging.getLogger("test"), clock=lambda: now[0]
    )
    placed = []
    for k in range(50):  # 5 s of clouds at 10 Hz, each arriving 0.1 s after its stamp
        now[0] = 100.0 + 0.1 * k
        msg = _cloud(jackal_points)
        msg.header.stamp = genpy.Time.from_sec(now[0] - 0.1)
        admission.receive("jackal", msg)
        cloud = admission.next_cloud(timeout_s=0)  # an insertion that keeps up
        if cloud is not None:
            placed.append(cloud.stamp_s)
    counts, waiting = admission.snapshot()["jackal"]
    # one every 0.5 s, from the first cloud's transform on: the map is at most ~1 s old, not frozen
    assert len(placed) >= 8 and placed == sorted(placed), placed
    assert max(b - a for a, b in zip(placed, placed[1:])) <= 0.61, placed
    assert counts.clouds_received == counts.clouds_placed + counts.clouds_superseded + waiting
    assert counts.clouds_dropped_tf == 0


def test_a_keyframe_is_placed_with_the_pose_sent_with_it_and_waits_for_it_never_for_tf(jackal_points):
    """A keyframe is from an outage, when no /tf crossed the link: tf2 answers at its stamp by
    interpolating across the gap (issue 39: the demo baseline's keyframes placed metres off the
    robots' paths, their hits in free space). It waits for its own pose, and without one it is
    dropped after the timeout, counted as tf, never placed by /tf."""
    now = [100.0]
    poses = {}
    looked_up = []

    def transform_of(frame, stamp):
        looked_up.append(stamp.to_sec())
        return JACKAL_POSE[1], JACKAL_POSE[0]  # /tf would answer (interpolated): it must not be asked

    def keyframe_pose_of(frame, stamp):
        if (frame, stamp.to_nsec()) not in poses:
            raise TransformUnavailable("its pose has not come")
        return poses.pop((frame, stamp.to_nsec()))

    admission = Admission(
        ["jackal"],
        transform_of,
        2.0,
        names.MAP_FRAME,
        logging.getLogger("test"),
        clock=lambda: now[0],
        keyframe_pose_of=keyframe_pose_of,
    )
    keyframe, lost = _cloud(jackal_points), _cloud(jackal_points)
    keyframe.header.stamp, lost.header.stamp = genpy.Time(90, 123456789), genpy.Time(91, 0)
    admission.receive("jackal", keyframe, backfill=True)
    assert admission.next_cloud(timeout_s=0) is None  # its pose has not come: it waits
    now[0] += 0.5
    pose = (JACKAL_POSE[1], (7.0, 8.0, 9.0))
    poses[(JACKAL_FRAME, keyframe.header.stamp.to_nsec())] = pose
    placed = admission.next_cloud(timeout_s=0)
    assert placed is not None and placed.backfill and placed.translation_m == (7.0, 8.0, 9.0)
    admission.receive("jackal", lost, backfill=True)
    assert admission.next_cloud(timeout_s=0) is None
    now[0] += 2.5  # past the timeout, no pose: dropped
    assert admission.next_cloud(timeout_s=0) is None
    counts, waiting = admission.snapshot()["jackal"]
    assert (counts.clouds_placed, counts.clouds_dropped_tf, waiting) == (1, 1, 0)
    assert looked_up == []
    live = _cloud(jackal_points)
    admission.receive("jackal", live)
    assert admission.next_cloud(timeout_s=0) is not None and len(looked_up) == 1  # live clouds: /tf


def test_backfill_keyframes_wait_in_their_own_fifo_behind_live_clouds(jackal_points):
    slots = RobotSlots(["a"], backfill_kept=2, clock=lambda: 0.0)
    keyframes = [Arrival("a", k, arrived_s=float(k), backfill=True) for k in range(3)]
    assert [slots.put(k) for k in keyframes[:2]] == [None, None]
    assert slots.put(keyframes[2]) is keyframes[0], "beyond the bound the oldest keyframe goes"
    slots.put(Arrival("a", "live", arrived_s=9.0))
    assert [slots.take(timeout_s=0).message for _ in range(3)] == ["live", 1, 2]
    assert slots.take(timeout_s=0) is None


def test_every_cloud_ends_in_one_counter_and_gaps_in_a_senders_numbers_are_missed(jackal_points):
    """The drop ledger: received = inserted + superseded + dropped by cause + waiting, and what the
    sender numbered but never delivered is missed."""
    server, _ = _server(robots=("jackal",), tf_timeout_s=0.0)
    good = [_compressed(jackal_points, 100 + k, seq=k) for k in range(8)]
    corrupt = _compressed(jackal_points, 120, seq=20)
    corrupt.compressed_data = b"\x00" * 40  # not Draco
    unplaced = _compressed(jackal_points, 121, seq=21, frame="jackal/nowhere")  # no transform
    frameless = _compressed(jackal_points, 122, seq=22, frame="")
    # 3, 4 and 6-19 never arrive; good[7] after seq 22: its sender restarted, no gap.
    stream = [good[0], good[1], good[2], good[5], corrupt, unplaced, frameless, good[7]]
    for msg in stream:
        server.receive_cloud("jackal", _as_received(msg))
        if msg.header.seq in (1, 5, 20, 21, 22):  # the insertion keeps up now and then
            drain(server)
    waiting = server.waiting("jackal")
    c = server.robot_counters("jackal")
    assert c.clouds_received == len(stream) and c.clouds_missed_upstream == 2 + 14
    assert (c.clouds_dropped_decoder, c.clouds_dropped_tf, c.clouds_dropped_invalid) == (1, 1, 1)
    assert c.clouds_inserted == 2 and c.clouds_superseded == 2 and waiting == 1
    assert c.clouds_accounted + waiting == c.clouds_received
    drain(server)
    c = server.robot_counters("jackal")
    assert c.clouds_accounted == c.clouds_received and c.clouds_inserted == 3


def test_bytes_of_another_type_are_dropped_by_the_decoder_cause(jackal_points):
    from std_msgs.msg import String

    server, _ = _server(robots=("jackal",))
    raw = _as_received(String(data="not a cloud"))
    server.receive_cloud("jackal", raw)
    drain(server)
    assert server.robot_counters("jackal").clouds_dropped_decoder == 1
    raw._connection_header = {}  # no type announced: read as the input's type, and it does not deserialize
    server.receive_cloud("jackal", raw)
    drain(server)
    assert server.robot_counters("jackal").clouds_dropped_decoder == 2


def test_a_raw_cloud_arrives_and_is_inserted_as_a_compressed_one_is(jackal_points):
    server, _ = _server(robots=("jackal",))
    server.receive_cloud("jackal", _as_received(_cloud(jackal_points)))
    assert server.insert_pending(timeout_s=0) == 1
    assert len(server.map.occupied_index()) > 0 and server.robot_counters("jackal").insertion_ms_avg > 0


def test_the_receive_process_shares_the_namespace_and_remaps_not_the_name_or_private_parameters():
    from cps_fleet import names
    from cps_mapping.admission_process import remappings_of

    ns = f"__ns:={names.absolute(names.TWIN_NS)}"
    argv = ["map_server", ns, "__name:=map_server_a", "__log:=/x.log", "_robots:=a,b", "x:=y"]
    argv += ["__master:=http://h:1", "--help"]
    assert remappings_of(argv) == (ns, "x:=y", "__master:=http://h:1")


FAST_START = """
import os, sys, threading, time
from cps_mapping import admission_process as ap
from cps_ros import priority, spare
if sys.argv[1] == "fast":
    ap.prepare_fast_start()
if sys.argv[1] == "spare":  # as a warm spare's import thread does it
    thread = threading.Thread(target=lambda: (priority.set_thread_nice(spare.SPARE_NICE), ap.prepare_fast_start()))
    thread.start()
    thread.join()
t0 = time.monotonic()
client = ap.AdmissionClient(
    ap.AdmissionConfig("fast_start_input", ap.remappings_of(sys.argv), ("jackal",), "map", 0.5, RECEIVE_NICE)
)
print("started_s", time.monotonic() - t0)
import rosgraph
print("registered_as", rosgraph.Master("/fast_start_test").lookupNode("/fast_ns/fast_start_input") is not None)
print("method", ap._start_context.get_start_method())
parent = int(open(f"/proc/{client.process.pid}/stat").read().rsplit(")", 1)[1].split()[1])
print("parent_is_me", parent == os.getpid())
print("nice", os.getpriority(os.PRIO_PROCESS, client.process.pid), os.getpriority(os.PRIO_PROCESS, parent))
client.close()
"""
RECEIVE_NICE = 2


@pytest.mark.ros
@pytest.mark.parametrize("start", ["fast", "spare", "spawn"])
def test_the_receive_process_starts_from_a_preloaded_fork_server_or_fresh(start, tmp_path):
    """A map server's warm spare prepares a fork server that imported what the receive process
    needs (issue 38: a restarted map server waited for those imports on the loaded twin CPU); the
    receive process is then its child, not the map server's, comes up in the map server's namespace
    (a fork server importing rospy under its own took the receive process to /: it heard nothing)
    and ends with it. Prepared at a spare's low priority (run as root here), the receive process still
    runs at the map server's nice plus its own ~receive_nice, not at the fork server's."""
    import subprocess
    import sys

    from cps_ros.processes import RosGraph, processes_named

    with RosGraph(log_dir=str(tmp_path)) as graph:
        result = subprocess.run(
            [sys.executable, "-c", FAST_START.replace("RECEIVE_NICE", str(RECEIVE_NICE)), start, "__ns:=/fast_ns"],
            env=graph.env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        port = graph.port
    assert result.returncode == 0, result.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in result.stdout.splitlines())
    print(f"receive process up after {float(lines['started_s']):.2f} s ({start})")
    forked = start in ("fast", "spare")
    assert lines["method"] == ("forkserver" if forked else "spawn")
    # in the map server's namespace, as rospy took it when the fork server imported it
    assert lines["registered_as"] == "True"
    # the fork server's child, not the map server's; the spawned one is the map server's
    assert lines["parent_is_me"] == ("False" if forked else "True")
    # the receive process at the map server's nice (0) plus its own; the spare's fork server at 19
    receive_nice, parent_nice = map(int, lines["nice"].split())
    assert receive_nice == RECEIVE_NICE
    assert parent_nice == (spare.SPARE_NICE if start == "spare" else 0)
    assert not processes_named("fast_start_input", f"127.0.0.1:{port}")


def test_a_fork_server_left_at_a_spares_priority_is_not_used_where_it_cannot_be_set_back(monkeypatch):
    """Where the supervisor did not set the spare's fork server back to the node's priority and the
    map server may not lower a nice value, the receive process is spawned: forked, it would run
    at SPARE_NICE on a loaded twin."""
    import multiprocessing
    import subprocess

    from cps_harness.testing import wait_for
    from cps_mapping import admission_process as ap
    from cps_ros import priority

    server = subprocess.Popen(["nice", "-n", str(spare.SPARE_NICE), "sleep", "30"])
    try:
        assert wait_for(lambda: priority.process_nice(server.pid) == spare.SPARE_NICE)  # nice has run
        monkeypatch.setattr(ap, "_start_context", multiprocessing.get_context("forkserver"))
        monkeypatch.setattr(ap, "_fork_server_pid", server.pid)
        monkeypatch.setattr(priority, "may_lower_nice_to", lambda nice: False)
        assert ap._context_for(2).get_start_method() == "spawn"
        assert ap._context_for(spare.SPARE_NICE).get_start_method() == "forkserver"  # not above
        monkeypatch.setattr(priority, "may_lower_nice_to", lambda nice: True)
        assert ap._context_for(2).get_start_method() == "forkserver"  # the child sets its own
        monkeypatch.setattr(ap, "_fork_server_pid", None)
        assert ap._context_for(2).get_start_method() == "spawn"  # no fork server known
    finally:
        server.kill()
        server.wait()


def test_stats_read_while_a_cloud_is_received_and_inserted_never_count_minus_one_waiting(jackal_points):
    """A cloud received and inserted while the statistics are read: read admission first, then the
    insertion, it was ended and never waiting, and the robot's queue_length came out -1. rospy
    could not serialize that uint32 and left the topic's buffer corrupt (a mission's statistics
    went silent for its last 7.6 s). Each figure is read in an order that cannot go negative."""
    server, published = _server(robots=("jackal",))
    real_snapshot = server.admission.snapshot
    raced = []

    def snapshot_then_a_cloud_arrives_and_is_inserted():
        taken = real_snapshot()
        if not raced:
            raced.append(1)
            server.receive_cloud("jackal", _as_received(_compressed(jackal_points, 200, seq=1)))
            assert server.insert_pending(timeout_s=0) == 1
        return taken

    server.admission.snapshot = snapshot_then_a_cloud_arrives_and_is_inserted
    server.publish_stats(genpy.Time(201, 0))
    (row,) = published["stats"][-1].robots
    assert raced and row.queue_length == 0
    published["stats"][-1].serialize(io.BytesIO())  # what rospy does with it
    assert server.waiting("jackal") == 0
    c = server.robot_counters("jackal")
    assert (c.clouds_received, c.clouds_inserted) == (1, 1)
