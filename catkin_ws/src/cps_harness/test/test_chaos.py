"""The chaos soak's pieces: the same seed draws the same faults; each invariant is judged from a
mission's CSV rows over the window after a fault, a missing value failing; the bridges' mismatch
counters read back; and a slow viewer on a heavy topic leaves the publisher's other subscriber fed."""

import json
import subprocess
import sys
import threading
import time

import pytest

from cps_fleet import names
from cps_harness import chaos
from cps_harness.testing import wait_for

ROBOTS = ("scout", "iris")
PROBE = names.absolute(names.COMMAND_PROBE)


def _cloud_topic(robot):
    return names.absolute(names.managed_cloud_at_twin(robot))


def test_the_same_seed_draws_the_same_faults_of_every_kind():
    faults = chaos.draw_faults(7, 60)
    assert faults == chaos.draw_faults(7, 60) and faults != chaos.draw_faults(8, 60)
    assert {f.kind for f in faults} == set(chaos.KINDS)
    cuts = [f.duration_s for f in faults if f.kind == chaos.LINK_CUT]
    assert all(chaos.CUT_S[0] <= d <= chaos.CUT_S[1] for d in cuts)
    assert all(f.target in chaos.KILL_TARGETS for f in faults if f.kind == chaos.KILL)
    with pytest.raises(ValueError):
        chaos.draw_faults(7, 0)


def test_faults_can_be_drawn_from_some_kinds_only():
    kills = chaos.draw_faults(7, 20, (chaos.KILL,))
    assert {f.kind for f in kills} == {chaos.KILL} and kills == chaos.draw_faults(7, 20, (chaos.KILL,))
    for kinds in ((), ("kil",)):
        with pytest.raises(ValueError, match="kinds must be some of"):
            chaos.draw_faults(7, 5, kinds)


def _window_rows(end, age_s=0.5, robots=ROBOTS, probe_ms=10.0):
    t = end + chaos.RECOVERY_S + 1.0
    ages = [{"time_s": str(t), "robot": r, "published_map_age_s": str(age_s)} for r in robots]
    arrivals = [{"topic": _cloud_topic(r), "robot": r, "receive_s": str(t)} for r in robots]
    probes = [{"topic": PROBE, "stamp_ns": str(int((t - probe_ms / 1000) * 1e9)), "receive_s": str(t)}]
    return ages, arrivals, probes


def _judge(end, ages, arrivals, probes):
    return chaos.judge_fault(chaos.Row(1, "test", end - 1, end), ROBOTS, ages, arrivals, probes, _cloud_topic, PROBE)


def _restart_lines(*events):
    from cps_bringup.supervisor import restart_note

    return "".join(f"[bringup] {label}: {restart_note(-9, n, limit, 1.0)}\n" for label, n, limit in events)


def test_a_kill_goes_to_a_process_with_a_restart_left_and_the_window_gives_them_back():
    """The supervisor ends the mission at a process's death past its restart limit in the window (a
    crash loop): the soak's kills never spend a process's last restart. cloud_throttle runs in
    cloud_tissue here, so both draw on one budget."""
    host = {"cloud_throttle": "cloud_tissue"}.get
    budget = chaos.RestartBudget(window_s=300.0)
    assert budget.target("cloud_tissue", lambda n: host(n, n), 0.0) == "cloud_tissue", "never restarted: a kill"
    log = _restart_lines(("cloud_tissue", 1, 3), ("map_server", 1, 3))
    budget.read(log, 10.0)
    log += _restart_lines(("cloud_tissue", 2, 3))
    budget.read(log, 40.0)
    budget.read(log, 50.0)  # lines read once
    assert budget.left("cloud_tissue", 50.0) == 1 and budget.left("map_server", 50.0) == 2
    assert budget.left("zenoh_bridge_twin", 50.0) is None
    log += _restart_lines(("cloud_tissue", 3, 3))
    budget.read(log, 60.0)
    assert budget.left("cloud_tissue", 60.0) == 0
    # spent: neither cloud_tissue nor its guest; the first target in KILL_TARGETS' order instead
    assert budget.target("cloud_throttle", lambda n: host(n, n), 60.0) == chaos.KILL_TARGETS[0]
    assert budget.target("map_server", lambda n: host(n, n), 60.0) == "map_server"
    # the window lets the first restart go
    assert budget.left("cloud_tissue", 310.0) == 1
    assert budget.target("cloud_tissue", lambda n: host(n, n), 310.0) == "cloud_tissue"


def test_no_kill_when_every_target_has_spent_its_restarts():
    budget = chaos.RestartBudget(window_s=300.0)
    budget.read(_restart_lines(*((t, 1, 1) for t in chaos.KILL_TARGETS)), 0.0)
    assert budget.target(chaos.KILL_TARGETS[2], lambda n: n, 1.0) is None


def test_a_fault_after_which_everything_recovers_holds():
    row = _judge(100.0, *_window_rows(100.0))
    assert row.held, row.failures
    assert row.map_age_max_s == 0.5 and row.teleop_probes == 1 and row.teleop_p95_ms == pytest.approx(10.0, abs=0.1)


def test_each_broken_invariant_is_named_and_a_missing_value_fails():
    ages, arrivals, probes = _window_rows(100.0, age_s=4.0, probe_ms=80.0)
    row = _judge(100.0, ages, arrivals[:1], probes)
    assert any("map not fresh" in f for f in row.failures) and any("no clouds from iris" in f for f in row.failures)
    assert any("teleop p95" in f for f in row.failures)
    row = _judge(100.0, ages[:1], arrivals, [])
    assert any("no map age recorded for iris" in f for f in row.failures)
    assert any("no teleop probe" in f for f in row.failures)
    # Rows before the window (during the fault) do not count.
    row = _judge(200.0, *_window_rows(100.0))
    assert not row.held and row.map_age_max_s is None


def test_mismatch_counters_read_back_and_only_growth_counts(tmp_path):
    path = tmp_path / "diag.jsonl"
    assert chaos.read_mismatch_counters(path) == {}
    lines = [
        {"node": "zenoh_bridge_twin", "key": "drop_md5_mismatch", "value": "0"},
        {"node": "zenoh_bridge_twin", "key": "drop_md5_mismatch", "value": "2"},
    ]
    path.write_text("".join(json.dumps(line) + "\n" for line in lines) + "not json\n")
    after = chaos.read_mismatch_counters(path)
    assert after == {"zenoh_bridge_twin/drop_md5_mismatch": 2.0}
    assert chaos.mismatch_growth({"zenoh_bridge_twin/drop_md5_mismatch": 2.0}, after) == {}
    assert chaos.mismatch_growth({}, after) == {"zenoh_bridge_twin/drop_md5_mismatch": 2.0}


def test_the_mismatch_keys_are_the_names_the_bridges_report():
    """The receive path's diagnostics keys (every kind, zeros included) hold each mismatch key it
    counts; the other two are the bridge's own counters, by the names it counts them with."""
    from cps_link.receive_path import PUBLISHER_TYPE_MISMATCH, SEND_TOPIC_TYPE_MISMATCH, ReceivePath

    reported = set(ReceivePath([], "cps", lambda msg_type: "").counters())
    own = [k for k in chaos.MISMATCH_KEYS if k not in reported]
    assert own == [SEND_TOPIC_TYPE_MISMATCH, PUBLISHER_TYPE_MISMATCH]


@pytest.mark.ros
def test_a_slow_viewer_reads_a_trickle_and_the_other_subscriber_stays_fed(rospy_node, ros_master):
    from std_msgs.msg import String

    topic = "/cps_test_heavy"
    pub = rospy_node.Publisher(topic, String, queue_size=2)
    got = []
    sub = rospy_node.Subscriber(topic, String, lambda _m: got.append(time.monotonic()))
    assert wait_for(lambda: pub.get_num_connections() >= 1, 10)
    stop = threading.Event()

    def publish():
        while not stop.is_set():
            pub.publish(String("x" * 500_000))
            stop.wait(0.05)  # 20 Hz, and ends at once when told

    publisher = threading.Thread(target=publish)
    publisher.start()
    try:
        before = len(got)
        viewer = subprocess.run(
            [sys.executable, "-m", "cps_harness.slow_viewer", topic, "4"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        fed = len(got) - before
    finally:
        stop.set()
        publisher.join()
        sub.unregister()
        pub.unregister()
    assert viewer.returncode == 0, viewer.stderr
    read = int(viewer.stdout.split()[1])
    assert 0 < read < 4 * 500_000, viewer.stdout  # connected, and read far less than was published
    assert fed >= 40, f"the other subscriber got {fed} messages in 4 s beside the slow viewer (~80 published)"
