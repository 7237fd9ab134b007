"""The bringup's plan and supervisor: wiring from fleet.yaml, and every failure path exits clearly
with nothing left running."""

import os
import re
import select
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from cps_bringup.plan import (
    CONTROL_TIER,
    DIGITAL,
    MAP_SERVER,
    MAP_SERVER_READY,
    MAP_TIER,
    NORMAL_TIER,
    PER_ROBOT,
    PHYSICAL,
    SHARED,
    TCPROS,
    ZENOH,
    NodeSpec,
    RunOptions,
    plan_nodes,
)
from cps_bringup.supervisor import BringupError, Supervisor
from cps_fleet import names
from cps_fleet.fleet import load_fleet
from cps_harness.testing import Gate, wait_for
from cps_ros.processes import RosGraph, processes_named
from cps_transport.cloud_levels import initial_leaf_m

pytestmark = pytest.mark.waiting

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "nodes", "cps_bringup")


def test_plan_wires_every_robot_through_the_tissue_to_the_map():
    fleet = load_fleet()
    specs = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", tissue_layout=PER_ROBOT))}
    for robot in fleet.robots:
        r = robot.name
        voxel = " ".join(specs[f"{r}/voxel_grid"].argv)
        assert f"{names.INPUT}:={names.absolute(names.robot_topic(r, robot.cloud_topic))} " in voxel
        assert f"{names.OUTPUT}:={names.absolute(names.robot_topic(r, names.POINTS_FILTERED))}" in voxel
        assert f"_leaf_size:={initial_leaf_m(fleet, robot)}" in voxel and "_filter_field_name:= " in voxel + " "
        throttle = specs[names.robot_topic(r, names.CLOUD_THROTTLE)].argv
        assert f"{names.OUTPUT}:={names.absolute(names.managed_cloud(r))}" in " ".join(throttle)
        assert f"__name:={names.CLOUD_THROTTLE}" in throttle
        # Exactly one subscriber of the managed topic crosses the link: the twin-side relay.
        relay = specs[f"{r}/link_relay"]
        assert relay.side == DIGITAL and relay.argv[3:5] == (
            names.absolute(names.managed_cloud(r)),
            names.absolute(names.managed_cloud_at_twin(r)),
        )
        crossing = [
            s.label
            for s in specs.values()
            if s.side == DIGITAL
            and s is not relay
            and any(names.absolute(names.managed_cloud(r)) == a.split(":=")[-1] for a in s.argv)
        ]
        assert crossing == [], crossing
        # The map server decodes what it inserts: no decoder process on the twin (issue 37).
        assert f"{r}/draco_decoder" not in specs and specs[f"{r}/draco_encoder"].side == PHYSICAL
        # The camera encodes its own video at the manager's level (cps_sim.video): no compressor.
        assert f"{r}/image_compressor" not in specs
    assert specs["map_server"].side == DIGITAL
    assert "_map_file:=/tmp/x/map.bt" in specs["map_server"].argv


def _arg(spec, key):
    return next(a.split(":=", 1)[1] for a in spec.argv if a.startswith(f"{key}:="))


def test_shared_plan_wires_every_robot_through_fixed_tissue_processes():
    """The default layout: one loader and one cloud_tissue carry every robot; the twin has no decoder."""
    fleet = load_fleet()
    specs = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", transport=ZENOH))}
    robots = fleet.robot_names
    assert not [
        label
        for label in specs
        if label.split("/")[-1]
        in ("voxel_grid", "draco_encoder", "cloud_throttle", "image_compressor", "draco_decoder", "backfill_decoder")
    ]
    for label, side in (("voxel_grid_loader", PHYSICAL), ("cloud_tissue", PHYSICAL)):
        assert specs[label].side == side and _arg(specs[label], "_robots") == ",".join(robots)
        assert _arg(specs[label], "_fleet_file") == fleet.path
    assert "cloud_decoder" not in specs
    assert _arg(specs["voxel_grid_loader"], "_manager") == names.absolute(names.TISSUE_NODELET_MANAGER)
    assert specs["voxel_grid_loader"].after == ("nodelet_manager",)
    for robot in fleet.robots:
        r = robot.name
        assert names.absolute(names.robot_topic(r, names.POINTS_FILTERED)) in specs["voxel_grid_loader"].wait_topics
        assert names.absolute(names.robot_topic(r, names.POINTS_DRACO)) in specs["cloud_tissue"].wait_topics
        assert (
            names.absolute(names.robot_topic(r, names.CAMERA_IMAGE_COMPRESSED)) not in specs["cloud_tissue"].wait_topics
        )  # the camera encodes it


def _with_copies(fleet, copies):
    """`fleet` with each robot also under `copies` new names (same type, leaf and route)."""
    import dataclasses

    extra = tuple(dataclasses.replace(r, name=f"{r.name}{i}") for i in range(2, copies + 2) for r in fleet.robots)
    return dataclasses.replace(fleet, robots=fleet.robots + extra)


@pytest.mark.parametrize("layout", ["shared", PER_ROBOT])
def test_tissue_processes_per_side_do_not_grow_with_the_fleet_in_the_shared_layout(layout):
    """4 and 8 robots: the same tissue processes on the robots' side when shared, more with every
    robot when per_robot (the per-robot cps_sim nodes are not the tissue); on the twin the same in
    both (over Zenoh: no relay, and the map server decodes)."""
    four = load_fleet()
    eight = _with_copies(four, 1)
    assert len(eight.robots) == 8

    def tissue(fleet):
        specs = plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", transport=ZENOH, tissue_layout=layout))
        return {
            side: sorted(
                s.label
                for s in specs
                if s.side == side and "cps_sim" not in " ".join(s.argv) and s.label != "fleet_sim"
            )
            for side in (PHYSICAL, DIGITAL)
        }

    small, large = tissue(four), tissue(eight)
    assert small[DIGITAL] == large[DIGITAL], "the twin has no per-robot tissue process (issue 37)"
    if layout == "shared":
        assert small[PHYSICAL] == large[PHYSICAL]
    else:
        assert len(large[PHYSICAL]) > len(small[PHYSICAL])


def test_plan_rejects_an_unknown_tissue_layout():
    with pytest.raises(ValueError, match="tissue_layout 'one'"):
        plan_nodes(load_fleet(), options=RunOptions(out_dir="/tmp/x", tissue_layout="one"))


def test_plan_for_real_robots_leaves_the_simulator_out():
    fleet = load_fleet()
    specs = plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x", simulate=False))
    labels = {s.label for s in specs}
    assert "fleet_sim" not in labels
    assert {"fleet_control", "voxel_grid_loader", "cloud_tissue"} <= labels
    assert all(s.after != ("fleet_sim",) for s in specs)


def test_plan_starts_the_clouds_once_the_map_server_is_ready():
    """Both sides: the map server is up only with its ~ready advertised, and the simulator (the
    clouds' source) starts after it; the physical side alone cannot wait for a remote twin."""
    fleet = load_fleet()
    both = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x"))}
    assert MAP_SERVER_READY in both[MAP_SERVER].wait_topics
    assert both["fleet_sim"].after == (MAP_SERVER,)
    physical = {s.label: s for s in plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x"))}
    assert physical["fleet_sim"].after == ()


def test_plan_control_layouts_shared_and_per_robot():
    fleet = load_fleet()
    shared = plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x"))
    control = [
        s
        for s in shared
        if "velocity_mux" in " ".join(s.argv) or "route_controller" in " ".join(s.argv) or s.label == "fleet_control"
    ]
    assert [s.label for s in control] == ["fleet_control"]
    argv = " ".join(control[0].argv)
    assert "__name:=fleet_control" in argv and f"_robots:={','.join(fleet.robot_names)}" in argv
    assert f"_fleet_file:={fleet.path}" in argv and "__ns" not in argv
    assert set(control[0].wait_topics) == {
        names.absolute(names.robot_topic(r, t)) for r in fleet.robot_names for t in (names.CMD_VEL, names.MISSION_STATE)
    }
    assert control[0].after == ("fleet_sim",)

    per_robot = plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x", control_layout="per_robot"))
    labels = {s.label for s in per_robot}
    assert "fleet_control" not in labels
    assert {f"{r}/{n}" for r in fleet.robot_names for n in ("velocity_mux", "route_controller")} <= labels
    with pytest.raises(ValueError, match="unknown control layout 'both'.*shared, per_robot"):
        plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x", control_layout="both"))


def test_plan_of_one_side_and_a_subset():
    fleet = load_fleet().with_robots(["jackal"])
    specs = plan_nodes(fleet, sides=(DIGITAL,), options=RunOptions(out_dir="/tmp/x"))
    assert {s.side for s in specs} == {DIGITAL}
    assert not any("scout" in s.label for s in specs)
    # the GUI shows this mission's robots only (issue 39: a monitoring mission sends back two)
    fleet = load_fleet().with_robots(["champ", "iris"])
    options = RunOptions(out_dir="/tmp/x", gui_screenshot_path="/tmp/x/gui.png")
    gui = next(s for s in plan_nodes(fleet, options=options) if s.label == "gui")
    assert gui.argv[gui.argv.index("--robots") + 1] == "champ,iris"


def test_plan_without_the_manager_and_with_the_command_probe():
    fleet = load_fleet()
    managed = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x"))}
    unmanaged = {s.label for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", bandwidth_manager=False))}
    assert "bandwidth_manager" in managed and "bandwidth_manager" not in unmanaged
    assert managed["command_probe"].side == DIGITAL
    assert any(names.absolute(names.COMMAND_PROBE) in arg for arg in managed["physical_stats"].argv)


def test_plan_starts_the_foxglove_endpoint_on_the_twin_unless_off():
    fleet = load_fleet()
    on = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", web_listen="0.0.0.0:9000"))}
    off = {s.label for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", web=False))}
    endpoint = on[names.FOXGLOVE_ENDPOINT]
    assert names.FOXGLOVE_ENDPOINT not in off
    assert endpoint.side == DIGITAL and not endpoint.essential and MAP_SERVER in endpoint.after
    assert "_listen:=0.0.0.0:9000" in endpoint.argv and f"__ns:={names.absolute(names.TWIN_NS)}" in endpoint.argv
    physical_only = plan_nodes(fleet, sides=(PHYSICAL,), options=RunOptions(out_dir="/tmp/x"))
    assert names.FOXGLOVE_ENDPOINT not in {s.label for s in physical_only}


def test_plan_records_mcap_and_only_the_links_streams_on_the_twin():
    from cps_bringup.mission_bag import record_topics
    from cps_bringup.plan import RECORDER
    from cps_web.mcap_recording import link_topics

    fleet = load_fleet()

    def recorder(**kw):
        return {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", **kw))}[RECORDER]

    bag = recorder(record_path="/tmp/x/m.bag")
    assert bag.argv[:2] == ("rosbag", "record") and bag.side == PHYSICAL
    full = recorder(record_path="/tmp/x/m.mcap")
    assert full.argv[1].endswith("mcap_recorder") and full.side == PHYSICAL
    assert f"_topics:={','.join(record_topics(fleet))}" in full.argv
    link = recorder(record_path="/tmp/x/m.mcap", record_link_only=True)
    cameras = [r.name for r in fleet.robots if r.has_depth_camera]
    assert link.side == DIGITAL and f"_topics:={','.join(link_topics(fleet.robot_names, cameras))}" in link.argv
    topics = link_topics(fleet.robot_names, cameras)
    assert names.absolute(names.managed_cloud_at_twin("scout")) in topics
    assert not any(t.endswith("/" + fleet.robot("scout").cloud_topic) for t in topics)  # no raw clouds


def test_plan_replays_a_bag_with_rosbag_play_and_an_mcap_with_cps_webs_player():
    from cps_bringup.mission_bag import replay_topics
    from cps_bringup.plan import REPLAY, REPLAY_DELAY_S

    fleet = load_fleet()

    def replay(path):
        return {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", replay_path=path))}[REPLAY]

    bag = replay("/tmp/x/m.bag")
    assert bag.argv[:3] == ("rosbag", "play", "--clock") and bag.side == PHYSICAL and bag.one_shot
    mcap = replay("/tmp/x/m.mcap")
    assert mcap.argv[1].endswith("mcap_player") and mcap.side == PHYSICAL and mcap.one_shot
    assert f"_topics:={','.join(replay_topics(fleet))}" in mcap.argv and f"_delay_s:={REPLAY_DELAY_S}" in mcap.argv
    # both stay up after the last message (their queues drain to slow subscribers): the mission ends them
    assert "--keep-alive" in bag.argv and "_keep_alive:=true" in mcap.argv
    assert mcap.after == bag.after and mcap.after  # after everything that is not waiting for its clouds
    # recorded too: the bag's player starts paused, the mission plays it once the recorder is
    # connected to its topics (a full run's MCAP lacked /scout/odom's first 2 messages)
    assert "--pause" not in bag.argv

    def recorded(path):
        options = RunOptions(out_dir="/tmp/x", replay_path=path, record_path="/tmp/x/r.mcap")
        return {s.label: s for s in plan_nodes(fleet, options=options)}[REPLAY]

    assert "--pause" in recorded("/tmp/x/m.bag").argv
    assert not any("pause" in a for a in recorded("/tmp/x/m.mcap").argv)  # cps_web's player keeps its delay


def _python_spec(label, code, wait_topics=(), restart_limit=0):
    return NodeSpec(
        label, PHYSICAL, (sys.executable, "-c", code), wait_topics=tuple(wait_topics), restart_limit=restart_limit
    )


@pytest.mark.ros
def test_a_node_that_never_comes_up_is_named_and_nothing_is_left(tmp_path):
    graph = RosGraph(log_dir=str(tmp_path))
    graph.start()
    port = graph.port
    supervisor = Supervisor(
        [_python_spec("lazy", "import time; print('starting'); time.sleep(600)", ["/never"])],
        graph,
        log=lambda *_: None,
    )
    try:
        with pytest.raises(BringupError) as info:
            supervisor.start_all(timeout_s=3)
    finally:
        supervisor.stop_all()
        graph.close()
    assert "not up after 3 s: lazy" in str(info.value)
    assert "topics not advertised: /never" in str(info.value)
    assert "| starting" in str(info.value)
    assert not processes_named(f"-p {port}", f"127.0.0.1:{port}")


TALKER = textwrap.dedent("""
    import rospy
    from std_msgs.msg import String
    rospy.init_node("flaky")
    pub = rospy.Publisher("/flaky/out", String, queue_size=1)
    rospy.sleep(1.0)
    raise SystemExit(4)
""")


@pytest.mark.ros
def test_a_dying_node_is_restarted_up_to_its_limit(tmp_path):
    events = []
    with RosGraph(log_dir=str(tmp_path)) as graph:
        supervisor = Supervisor(
            [_python_spec("flaky", TALKER, ["/flaky/out"], restart_limit=1)], graph, log=events.append
        )
        try:
            supervisor.start_all(timeout_s=30)
            with pytest.raises(BringupError, match=r"flaky exited with code 4 \(restarted 1 of 1 times\)"):
                for _ in range(200):
                    supervisor.poll()
                    time.sleep(0.1)
        finally:
            supervisor.stop_all()
    assert any("restart 1/1" in e for e in events)


SPARED_NODE = textwrap.dedent("""
    import os, sys

    def preload():
        import rospy  # noqa: F401
        from std_msgs.msg import String  # noqa: F401

    def main():
        import rospy
        from std_msgs.msg import String
        rospy.init_node("spared")
        pub = rospy.Publisher("/spared/out", String, queue_size=1, latch=True)
        pub.publish(String(str(os.getpid())))
        rospy.spin()

    if __name__ == "__main__":
        sys.exit(main())
""")


def _poll_until(supervisor, condition, timeout_s=30.0):
    """Poll `supervisor` until `condition()` holds (True) or `timeout_s` passes (False); between polls
    it waits as its run loop does (`wait_for_exit`: woken by a node's death)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        supervisor.poll()
        if condition():
            return True
        supervisor.wait_for_exit(0.05)
    return False


def _kill_and_wait_for_exit(*pids, timeout_s=10.0):
    """SIGKILL each process and return once every one has exited (its pidfd turns readable)."""
    fds = [os.pidfd_open(pid) for pid in pids]
    try:
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
        waiting, deadline = list(fds), time.monotonic() + timeout_s
        while waiting and time.monotonic() < deadline:
            readable, _, _ = select.select(waiting, [], [], deadline - time.monotonic())
            waiting = [fd for fd in waiting if fd not in readable]
        assert not waiting, f"still running {timeout_s} s after SIGKILL: {pids}"
    finally:
        for fd in fds:
            os.close(fd)


def _slow_spared_node(tmp_path):
    """The spared node whose spare's imports last until its gate (a FIFO) is released: (spec, gate)."""
    gate = Gate(tmp_path / "imports_may_finish")
    script = tmp_path / "spared_node"
    slow_preload = f"def preload():\n    open({gate.path!r}).close()\n\n\n"
    script.write_text(SPARED_NODE.replace("def preload():", slow_preload + "def unused():", 1))
    return NodeSpec("spared", PHYSICAL, (sys.executable, str(script)), wait_topics=("/spared/out",), spare=True), gate


@pytest.mark.ros
def test_a_killed_node_restarts_from_its_warm_spare_and_gets_a_new_one(tmp_path, monkeypatch):
    """Issue 38: a kill's recovery was a Python node's imports on a loaded CPU. The node's spare
    waits imported, is not the node (the chaos soak's process count leaves it out), becomes it on
    the restart, and a new spare follows; a dead spare means a cold start; nothing is left."""
    from cps_bringup import supervisor as supervisor_module
    from cps_ros import spare as spares

    monkeypatch.setattr(supervisor_module, "SPARE_AFTER_UP_S", 0.5)
    script = tmp_path / "spared_node"
    script.write_text(SPARED_NODE)
    spec = NodeSpec("spared", PHYSICAL, (sys.executable, str(script)), wait_topics=("/spared/out",), spare=True)
    events = []
    with RosGraph(log_dir=str(tmp_path)) as graph:
        port = graph.port
        supervisor = Supervisor([spec], graph, log=events.append, warm_spares=True)
        running = supervisor.running

        def poll_until(condition, timeout_s=30.0):
            return _poll_until(supervisor, condition, timeout_s)

        def waiting_spare():
            r = running["spared"]
            return r.spare is not None and spares.is_ready_spare(r.spare.pid)

        try:
            supervisor.start_all(timeout_s=30)
            assert poll_until(waiting_spare), events
            first, spare_pid = supervisor.pid_of("spared"), running["spared"].spare.pid
            os.kill(first, signal.SIGKILL)
            assert poll_until(lambda: running["spared"].up and supervisor.pid_of("spared") != first), events
            assert supervisor.pid_of("spared") == spare_pid and "spared: restarted from its warm spare" in events[-1]
            assert poll_until(lambda: not spares.is_waiting_spare(spare_pid))  # it is the node now
            assert poll_until(waiting_spare), events  # and a new one waits
            # a spare killed with its node (as a soak's kill by command line would): a cold start. Both
            # have exited before the supervisor looks again; else (CI, a92101b) a node slow to die on a
            # loaded CPU stayed "up" past SPARE_AFTER_UP_S and its next spare took over, rightly.
            second = supervisor.pid_of("spared")
            _kill_and_wait_for_exit(running["spared"].spare.pid, second)
            assert poll_until(lambda: running["spared"].up and supervisor.pid_of("spared") != second), events
            assert poll_until(waiting_spare), events
        finally:
            supervisor.stop_all()
    assert sum("warm spare" in e for e in events) == 1
    assert not processes_named(f"-p {port}", f"127.0.0.1:{port}", str(script))


@pytest.mark.ros
def test_a_spare_still_importing_is_started_at_the_nodes_priority(tmp_path, monkeypatch):
    """A spare's imports run at SPARE_NICE and on a saturated side may not finish before its node dies
    (a chaos soak's robots' spares): the supervisor (root here) gives it the node's priority and
    starts it; the node comes up from it once its imports are done."""
    from cps_bringup import supervisor as supervisor_module
    from cps_ros import spare as spares

    monkeypatch.setattr(supervisor_module, "SPARE_AFTER_UP_S", 0.5)
    spec, gate = _slow_spared_node(tmp_path)
    events = []
    with RosGraph(log_dir=str(tmp_path)) as graph:
        supervisor = Supervisor([spec], graph, log=events.append, warm_spares=True)
        running = supervisor.running

        def poll_until(condition, timeout_s=30.0):
            return _poll_until(supervisor, condition, timeout_s)

        try:
            supervisor.start_all(timeout_s=30)
            assert poll_until(
                lambda: running["spared"].spare is not None and spares.is_waiting_spare(running["spared"].spare.pid)
            )
            first, spare_pid = supervisor.pid_of("spared"), running["spared"].spare.pid
            assert not spares.is_ready_spare(spare_pid)
            os.kill(first, signal.SIGKILL)
            assert poll_until(lambda: supervisor.pid_of("spared") != first), events
            assert supervisor.pid_of("spared") == spare_pid
            assert "spared: restarted from its warm spare (still importing" in events[-1], events
            assert os.getpriority(os.PRIO_PROCESS, spare_pid) == 0
            gate.release()
            assert poll_until(lambda: running["spared"].up), events
        finally:
            gate.release()
            supervisor.stop_all()
            gate.close()


@pytest.mark.ros
def test_a_spare_that_imports_too_long_gets_its_nodes_priority(tmp_path, monkeypatch):
    """On a saturated side a spare at SPARE_NICE might never be ready: after SPARE_PROMOTE_AFTER_S it
    imports at its node's priority (root here); a spare that is ready by then is left as it is."""
    from cps_bringup import supervisor as supervisor_module
    from cps_ros import spare as spares

    monkeypatch.setattr(supervisor_module, "SPARE_AFTER_UP_S", 0.2)
    monkeypatch.setattr(supervisor_module, "SPARE_PROMOTE_AFTER_S", 1.0)
    spec, gate = _slow_spared_node(tmp_path)
    with RosGraph(log_dir=str(tmp_path)) as graph:
        supervisor = Supervisor([spec], graph, log=lambda *_: None, warm_spares=True)
        try:
            supervisor.start_all(timeout_s=30)
            running = supervisor.running["spared"]
            assert _poll_until(supervisor, lambda: running.spare is not None, 10)
            pid = running.spare.pid

            def nices():
                return [os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir(f"/proc/{pid}/task")]

            assert wait_for(lambda: spares.SPARE_NICE in nices(), timeout_s=10), nices()
            assert not spares.is_ready_spare(pid)  # importing at 19
            assert _poll_until(supervisor, lambda: running.spare_promote_at is None, 10)
            assert set(nices()) == {0} and running.spare.pid == pid
        finally:
            gate.release()
            supervisor.stop_all()
            gate.close()


@pytest.mark.ros
def test_the_wait_between_polls_ends_when_a_node_dies(tmp_path):
    """wait_for_mission's wait wakes at a node's death (its pidfd), not at the end of its period, so
    that the restart is not delayed by up to a period; without a death it waits the period."""
    with RosGraph(log_dir=str(tmp_path)) as graph:
        supervisor = Supervisor([_python_spec("sleeper", "import time; time.sleep(600)")], graph, log=lambda *_: None)
        try:
            supervisor.start_all(timeout_s=30)
            t0 = time.monotonic()
            supervisor.wait_for_exit(1.0)
            assert time.monotonic() - t0 >= 0.9
            killer = threading.Timer(0.5, os.kill, (supervisor.pid_of("sleeper"), signal.SIGKILL))
            killer.start()
            t0 = time.monotonic()
            supervisor.wait_for_exit(60.0)
            assert time.monotonic() - t0 < 30.0 and supervisor.running["sleeper"].proc.poll() == -signal.SIGKILL
        finally:
            supervisor.stop_all()


def _run_cli(*args, timeout=60):
    return subprocess.run([sys.executable, BRINGUP, *args], capture_output=True, text=True, timeout=timeout)


def test_cli_unknown_robot_fails_clearly():
    result = _run_cli("all", "--robots", "scout,tank", "--out", "/tmp/cps-cli-test")
    assert result.returncode == 2
    assert "unknown robot(s) tank; the fleet has scout, jackal, champ, iris" in result.stderr


def test_cli_malformed_fleet_file_names_the_line(tmp_path):
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text("profile: light\nprofiles: [\n")
    result = _run_cli("all", "--fleet", str(fleet), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert f"{fleet}:" in result.stderr and "YAML syntax error" in result.stderr


def test_cli_port_in_use_fails_clearly(tmp_path):
    with socket.socket() as sock:
        sock.bind(("0.0.0.0", 0))
        sock.listen()
        port = sock.getsockname()[1]
        result = _run_cli("digital", "--port", str(port), "--out", str(tmp_path))
    assert result.returncode == 2
    assert f"port {port} is in use" in result.stderr


def test_shipped_launch_files_are_the_plan_and_parse_with_roslaunch():
    from cps_bringup.launch_xml import shipped_launch_files

    launch_dir = os.path.join(os.path.dirname(__file__), "..", "launch")
    for name, text in shipped_launch_files().items():
        with open(os.path.join(launch_dir, name)) as stream:
            assert stream.read() == text, f"{name} is stale: run python -m cps_bringup.launch_xml"
    listed = subprocess.run(
        ["roslaunch", "--nodes", "cps_bringup", "all.launch"], capture_output=True, text=True, timeout=60
    )
    assert listed.returncode == 0, listed.stderr
    nodes = set(listed.stdout.split())
    assert {
        "/fleet_sim",
        names.absolute(names.in_twin(names.MAP_SERVER)),
        "/cloud_tissue",
        "/voxel_grid_loader",
    } <= nodes
    assert len(nodes) == len(plan_nodes(load_fleet(), options=RunOptions(out_dir="/tmp/x")))


def test_a_new_mission_starts_without_the_previous_missions_map_and_csvs(tmp_path):
    from cps_bringup.cli import clear_previous_mission

    for name in ("map.bt", "stats.csv", "allocation.csv", "gui.png", "physical_stats.csv", "notes.txt"):
        (tmp_path / name).write_text("from an earlier mission")
    (tmp_path / "logs").mkdir()
    assert sorted(clear_previous_mission(str(tmp_path), (DIGITAL,))) == [
        "allocation.csv",
        "gui.png",
        "map.bt",
        "stats.csv",
    ]
    # The physical side's file stays for a physical twin started on its own into the same folder,
    # and nothing the missions do not write is touched.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["logs", "notes.txt", "physical_stats.csv"]
    assert clear_previous_mission(str(tmp_path), (PHYSICAL, DIGITAL)) == ["physical_stats.csv"]


def test_every_file_the_plan_writes_into_the_folder_is_cleared_by_a_new_mission(tmp_path):
    """A node's file in the output folder that clear_previous_mission does not know is appended to by
    the next mission into that folder (link_estimate.csv was, till 2026-11-30)."""
    from cps_bringup.cli import MISSION_OUTPUTS

    out = str(tmp_path)
    written = {PHYSICAL: set(), DIGITAL: set()}
    for transport, layout in ((TCPROS, SHARED), (ZENOH, PER_ROBOT)):
        options = RunOptions(out_dir=out, transport=transport, tissue_layout=layout, gui_screenshot_path=None)
        for spec in plan_nodes(load_fleet(), options=options):
            for arg in spec.argv:
                value = arg.split(":=", 1)[-1]
                if os.path.dirname(value) == out:
                    written[spec.side].add(os.path.basename(value))
    assert "link_estimate.csv" in written[DIGITAL] and "physical_stats.csv" in written[PHYSICAL]
    for side, files in written.items():
        assert files <= set(MISSION_OUTPUTS[side]), (side, sorted(files - set(MISSION_OUTPUTS[side])))


@pytest.mark.parametrize("simulate, replay", [(True, ""), (True, "/tmp/x.bag"), (False, "")])
def test_a_camera_compressor_runs_only_without_the_simulated_camera(simulate, replay):
    """fleet_sim's camera sends the managed video itself; a replayed bag or real robots' raw images
    become the managed video in a compressor per depth robot."""
    fleet = load_fleet()
    options = RunOptions(out_dir="/tmp/x", transport=ZENOH, simulate=simulate, replay_path=replay)
    specs = {s.label: s for s in plan_nodes(fleet, options=options)}
    for robot in fleet.robots:
        compressor = specs.get(f"{robot.name}/image_compressor")
        if simulate and not replay or not robot.has_depth_camera:
            assert compressor is None
        else:
            assert f"_robot:={robot.name}" in compressor.argv and compressor.side == PHYSICAL


def test_the_unmanaged_arm_sends_the_finest_video_and_the_operators_robot_reaches_the_manager():
    """--bandwidth-manager off: the cameras start at the finest video at the maximum rate (nobody
    will lower them); with the manager, --select-robot becomes its ~selected_robot. Over Zenoh each
    side runs a main and a command bridge, and the twin measures the cameras' video."""
    fleet = load_fleet()
    off = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", bandwidth_manager=False))}
    assert "bandwidth_manager" not in off and _arg(off["fleet_sim"], "_video_unmanaged") == "true"
    on = {
        s.label: s
        for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", transport=ZENOH, selected_robot="jackal"))
    }
    assert _arg(on["fleet_sim"], "_video_unmanaged") == "false"
    assert _arg(on["bandwidth_manager"], "_selected_robot") == "jackal"
    assert {
        "zenoh_bridge_robots",
        "zenoh_bridge_robots_command",
        "zenoh_bridge_twin",
        "zenoh_bridge_twin_command",
    } <= set(on)
    assert "--lane" in on["zenoh_bridge_twin_command"].argv
    assert on["zenoh_bridge_twin_command"].tier == CONTROL_TIER and on["zenoh_bridge_twin"].tier == NORMAL_TIER
    assert on[MAP_SERVER].tier == MAP_TIER
    cameras = [r.name for r in fleet.robots if r.has_depth_camera]
    assert _arg(on["topic_stats"], "_topics").count("/" + names.CAMERA_IMAGE_COMPRESSED) == len(cameras)
    assert all(
        names.absolute(names.robot_topic(r, names.CAMERA_IMAGE_COMPRESSED))
        in _arg(on["topic_stats"], "_arrival_topics")
        for r in cameras
    )


def test_selecting_a_robot_without_a_camera_is_refused_before_anything_starts(tmp_path):
    from cps_bringup.cli import build_parser, run_mission

    args = build_parser().parse_args(["all", "--select-robot", "scout", "--out", str(tmp_path / "out")])
    with pytest.raises(BringupError, match=r"--select-robot scout: not a camera robot .*camera robots: jackal"):
        run_mission(args, log=lambda _line: None)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["all", "--web-listen", "8765"], "--web-listen: listen address '8765': expected host:port"),
        (["all", "--record-link-only"], "--record-link-only: give the file with --record"),
        (["physical", "--record", "x.mcap", "--record-link-only"], "records what the twin receives"),
        # split across machines the robots' command-lane listener must be named too (issue 38)
        (["physical", "--twin-address", "10.0.0.2"], "--twin-address and --robots-address go together"),
        (["digital", "--robots-address", "10.0.0.1"], "--twin-address and --robots-address go together"),
    ],
)
def test_bad_web_and_recording_options_are_refused_before_anything_starts(tmp_path, argv, message):
    from cps_bringup.cli import build_parser, run_mission

    args = build_parser().parse_args([*argv, "--out", str(tmp_path / "out")])
    with pytest.raises(BringupError, match=re.escape(message)):
        run_mission(args, log=lambda _line: None)
    assert not (tmp_path / "out").exists()


def test_announcing_the_link_capacity_without_a_tc_link_or_without_the_twin_is_refused_before_anything_starts(
    tmp_path,
):
    from cps_bringup.cli import build_parser, run_mission

    out = tmp_path / "out"
    for argv, match in (
        (["all", "--announce-link-capacity"], "use it with --link RATE or --link-scenario NAME"),
        (["physical", "--link", "20mbit", "--announce-link-capacity"], "where the bandwidth manager runs"),
    ):
        args = build_parser().parse_args([*argv, "--out", str(out)])
        with pytest.raises(BringupError, match=match):
            run_mission(args, log=lambda _line: None)
        assert not out.exists()


def test_the_mission_result_says_what_the_budget_came_from_when_nothing_was_announced():
    from types import SimpleNamespace

    from cps_bringup.cli import _unannounced

    link = SimpleNamespace(measured_mbps=55.24)
    fleet = load_fleet()
    assert fleet.link.estimate_bandwidth  # the default: the online estimate, over the Zenoh bridges
    zenoh, tcpros = RunOptions(out_dir="/x", transport=ZENOH), RunOptions(out_dir="/x", transport=TCPROS)
    assert _unannounced(link, zenoh, fleet) == (
        "not announced: the manager's online estimate from the bridges' link reports, seeded by iperf3's "
        "55.2 Mbit/s at the start"
    )
    # over TCPROS no bridge reports the link: bringup turns the estimate off
    assert _unannounced(link, tcpros, fleet) == (
        "not announced: the manager's budget from iperf3's 55.2 Mbit/s at the start"
    )
    assert _unannounced(None, tcpros, fleet) == "not announced: the manager's budget from the configured capacity"
    assert (
        _unannounced(link, RunOptions(out_dir="/x", bandwidth_manager=False), fleet)
        == "not announced (no bandwidth manager)"
    )


def test_a_video_trace_reaches_fleet_sim_only_when_asked():
    """--video-trace: fleet_sim's ~video_trace; without it no parameter (the cameras render live, and
    the launch files, written from the default plan, do not change)."""
    fleet = load_fleet()
    trace = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x", video_trace="/runs/t.npz"))}
    assert _arg(trace["fleet_sim"], "_video_trace") == "/runs/t.npz"
    live = {s.label: s for s in plan_nodes(fleet, options=RunOptions(out_dir="/tmp/x"))}
    assert not any(a.startswith("_video_trace:=") for a in live["fleet_sim"].argv)


def test_a_video_trace_that_cannot_feed_the_fleets_cameras_is_refused_before_anything_starts(tmp_path):
    from cps_bringup.cli import build_parser, run_mission
    from cps_sim.video_trace import record_video_trace

    trace = str(tmp_path / "jackal.npz")
    record_video_trace(load_fleet(profile="light").with_robots(["jackal"]), trace, 2, log=lambda _: None)
    out = tmp_path / "out"
    args = build_parser().parse_args(["all", "--profile", "light", "--video-trace", trace, "--out", str(out)])
    with pytest.raises(
        BringupError, match=r"--video-trace: video trace .* does not match .*camera robot 'champ'"
    ) as error:
        run_mission(args, log=lambda _line: None)
    assert trace in str(error.value) and not out.exists()
    args = build_parser().parse_args(["all", "--no-sim", "--video-trace", trace, "--out", str(out)])
    with pytest.raises(BringupError, match="--video-trace feeds the simulated cameras"):
        run_mission(args, log=lambda _line: None)
    assert not out.exists()


def test_a_process_naming_the_mission_folder_after_the_stop_is_killed_and_named(tmp_path):
    import subprocess
    import sys

    from cps_bringup.cli import _kill_leftovers
    from cps_harness.testing import processes_named, wait_for

    out = tmp_path / "mission"
    out.mkdir()
    left = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", str(out)], start_new_session=True)
    lines = []
    try:
        # Between fork and exec the child still shows pytest's command line: wait until it names the folder.
        assert wait_for(lambda: processes_named(str(out)), timeout_s=10)
        _kill_leftovers(str(out), lines.append)
        left.wait(10)
        assert left.returncode == -9
        assert len(lines) == 1 and "1 process(es) of this mission outlived their stop" in lines[0], lines
        assert f"time.sleep(60) {out}" in lines[0]
        lines.clear()
        _kill_leftovers(str(out), lines.append)  # nothing left: nothing said
        assert lines == []
    finally:
        if left.poll() is None:
            left.kill()
            left.wait()


@pytest.mark.parametrize("stop_on_signals", [True, False])
def test_the_bringup_stops_on_sigint_even_when_started_with_it_ignored(stop_on_signals):
    """A process started in the background of a non-interactive shell inherits SIGINT ignored, and
    Python keeps ignoring it: the chaos soak's bringup did not stop on its harness's SIGINT. The
    bringup installs its handler itself (cli._stop_on_signals); without it the SIGINT is lost."""
    code = (
        "import sys, time\n"
        "from cps_bringup.cli import _stop_on_signals\n"
        f"if {stop_on_signals}:\n"
        "    _stop_on_signals()\n"
        "print('ready', flush=True)\n"
        "try:\n"
        "    time.sleep(30)\n"
        "except KeyboardInterrupt:\n"
        "    sys.exit(130)\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGINT)
        if stop_on_signals:
            assert proc.wait(5) in (130, -signal.SIGINT)  # -2: interrupted before its try
        else:
            time.sleep(1.0)
            assert proc.poll() is None, "the premise: an inherited SIG_IGN outlives Python's start"
    finally:
        proc.kill()
        proc.wait()
