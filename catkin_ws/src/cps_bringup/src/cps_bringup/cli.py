"""`cps_bringup physical|digital|all`: start a side (or both) of the system and run the mission.

Starts a private roscore (unless --master-uri points at the other side's), the side's nodes with
parameters from fleet.yaml, waits until each is up, restarts what dies, prints progress, and on
Ctrl-C or the end of the mission stops everything. With --link, the physical and digital twins
run in two network namespaces joined by a shaped link (cps_link), like the paper's Wi-Fi.
"""

import argparse
import contextlib
import dataclasses
import os
import signal
import sys
import time
from typing import Dict, List, Optional

from cps_bringup.host_split import HostSplitError
from cps_bringup.mission import MissionMonitor, wait_for_mission
from cps_bringup.plan import (
    CONTROL_LAYOUTS,
    DIGITAL,
    GUI_SCREENSHOT_AFTER_S,
    MAP_SERVER,
    MAP_SERVER_READY,
    PHYSICAL,
    RECORDER,
    SHARED,
    TCPROS,
    TISSUE_LAYOUTS,
    TRANSPORTS,
    WEB_LISTEN,
    WEB_URL_FILE,
    ZENOH,
    RunOptions,
    plan_nodes,
    replay_starts_paused,
)
from cps_bringup.privileges import (
    PrivilegeError,
    check_code_readable,
    ensure_map_kernels,
    hand_over,
    node_user,
    user_env,
    user_prefix,
)
from cps_bringup.supervisor import (
    BringupError,
    Event,
    MasterLost,
    RestartPolicy,
    Supervisor,
    ensure_port_free,
    node_log_dir,
)
from cps_fleet import names
from cps_fleet.config import ConfigError
from cps_fleet.fleet import PROFILES, load_fleet, robot_names_arg
from cps_ros.processes import RosGraph, free_port
from cps_sim.renderers import DEFAULT_RENDERER, RENDERERS

# The exit code when the ROS master died mid-mission: the map was saved (if the map server could)
# and everything stopped; the run is not restarted (docs/reliability.md).
EXIT_MASTER_LOST = 3
MASTER_LOST = "master_lost"
# How long the map server may take to save on SIGINT when the master is gone.
MAP_SAVE_ON_SHUTDOWN_TIMEOUT_S = 20.0


@dataclasses.dataclass
class MissionResult:
    out_dir: str
    ended_by: str
    elapsed_s: float
    link: str
    map_file: Optional[str]
    progress: object
    events: List[Event]
    restarts: Dict[str, int]
    host_split: str = "no host split (not asked)"
    video_source: str = "not recorded"
    link_capacity: str = "not recorded"


def build_parser():
    parser = argparse.ArgumentParser(prog="cps_bringup", description=__doc__.split("\n\n")[0])
    parser.add_argument("side", choices=("physical", "digital", "all"))
    parser.add_argument("--fleet", default=None, help="fleet.yaml (default: cps_bringup/config/fleet.yaml)")
    parser.add_argument("--profile", choices=PROFILES, default=None, help="sensor profile (default: fleet.yaml's)")
    parser.add_argument("--robots", default=None, help="comma-separated subset of the fleet, e.g. scout,jackal")
    parser.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S seconds even if routes are not done (default: run until all done)",
    )
    parser.add_argument("--out", default="out/mission", help="output folder (logs, CSVs, map)")
    parser.add_argument("--port", type=int, default=None, help="roscore port (default: a free one)")
    parser.add_argument(
        "--master-uri",
        default=None,
        help="join this master instead of starting one (split physical/digital across machines)",
    )
    parser.add_argument(
        "--link",
        default="none",
        metavar="RATE",
        help="run the twins across a link shaped to this tc rate, e.g. 20mbit (needs root); 'none' = loopback",
    )
    parser.add_argument(
        "--link-scenario",
        default=None,
        metavar="NAME",
        help="run a cps_link scenario (capacity steps, outages; cps_link/config/scenarios/NAME.yaml "
        "or a path) on the link during the mission; implies --link at its initial rate",
    )
    parser.add_argument(
        "--announce-link-capacity",
        action="store_true",
        help="publish the link's capacity as tc sets it (the scenario's initial rate, then each rate step; "
        "never an outage) on /tissue/link_capacity, where the bandwidth manager makes its budget from it: "
        "the paper's known-capacity assumption (needs --link or --link-scenario, and the twin's side here)",
    )
    parser.add_argument(
        "--transport",
        choices=TRANSPORTS,
        default=ZENOH,
        help="zenoh: a master per side, joined only by cps_link's mutual-TLS bridges; "
        "tcpros: one master across the link (the paper's set-up)",
    )
    parser.add_argument(
        "--control-layout",
        choices=CONTROL_LAYOUTS,
        default=RunOptions.control_layout,
        help="the robots' velocity mux and route controller: shared (one fleet_control process "
        "for every robot) or per_robot (a velocity_mux and a route_controller per robot)",
    )
    parser.add_argument(
        "--twin-address",
        default=None,
        help="zenoh: the twin host's address, where its main-lane bridge listens (default: the link's "
        "twin address, or 127.0.0.1)",
    )
    parser.add_argument(
        "--robots-address",
        default=None,
        help="zenoh: the robots' host's address, where its command-lane bridge listens (default: the "
        "link's robots' address, or 127.0.0.1)",
    )
    parser.add_argument("--link-name", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--host-cpus",
        default=None,
        metavar="robots=CPUS,twin=CPUS",
        help="run the robots' side and the twin side on separate CPUs (cgroup v1 cpuset+cpu as root, else "
        "taskset), e.g. robots=0,twin=1 or robots=0-2,twin=3; 'none': no split (default: split the CPUs in "
        "halves for --link runs as root, no split otherwise)",
    )
    parser.add_argument(
        "--host-quota",
        default=None,
        metavar="SIDE=CORES",
        help="a side's CFS quota in cores on top of its CPUs, e.g. twin=0.5 (cgroups only)",
    )
    parser.add_argument("--screenshot", action="store_true", help="start the GUI offscreen and save a screenshot")
    parser.add_argument("--screenshot-after", type=float, default=GUI_SCREENSHOT_AFTER_S, metavar="S")
    parser.add_argument("--start-timeout", type=float, default=150.0, metavar="S")
    parser.add_argument(
        "--renderer",
        choices=RENDERERS,
        default=DEFAULT_RENDERER,
        help="sensor renderer: fast (moderngl on EGL + Embree; falls back to PyBullet's without "
        "EGL), or PyBullet's egl, tiny, auto (TinyRenderer for small images, EGL for 640x480)",
    )
    parser.add_argument(
        "--no-sim",
        action="store_true",
        help="real robots: do not start fleet_sim; their drivers publish /<r>/points, odom, tf",
    )
    parser.add_argument(
        "--run-as",
        default=None,
        metavar="USER",
        help="user the nodes run as when started as root (default: nobody; 'root' keeps root)",
    )
    parser.add_argument(
        "--baseline",
        default=None,
        metavar="MAP.bt",
        help="monitoring mission: compare the new map with this earlier one of the site, live",
    )
    parser.add_argument(
        "--site-changes",
        default=None,
        metavar="FILE",
        help="monitoring mission in simulation: equipment removed/moved/added (YAML, see "
        "cps_bringup/config/site_changes.yaml); needs --baseline",
    )
    parser.add_argument(
        "--record",
        default=None,
        metavar="BAG|FILE.mcap",
        help="record the mission (sensor, odometry, tf topics and the twin's managed inputs) "
        "to this rosbag with rosbag record, or, for a name ending in .mcap, to MCAP with the ROS 1 message "
        "definitions (cps_web's recorder: Foxglove, Lichtblick and the mcap tools read it)",
    )
    parser.add_argument(
        "--record-link-only",
        action="store_true",
        help="with --record: only what crosses the link, as the twin receives it (the managed clouds and "
        "video, tf, odometry, battery, joint states, mission state), recorded on the twin's side",
    )
    parser.add_argument(
        "--web",
        choices=("on", "off"),
        default="on",
        help="the twin's Foxglove WebSocket endpoint (cps_web) for Foxglove or Lichtblick: map, poses and "
        "trails, change clusters, the selected robot's video, fleet health, the link (default: on)",
    )
    parser.add_argument(
        "--web-listen",
        default=WEB_LISTEN,
        metavar="HOST:PORT",
        help=f"where the endpoint listens (default {WEB_LISTEN}: the twin's host only; port 0: any free one, "
        f"written to <out>/{WEB_URL_FILE})",
    )
    parser.add_argument(
        "--replay",
        default=None,
        metavar="BAG|FILE.mcap",
        help="physical side: play this mission bag (e.g. your own robot's) with rosbag play, or a ROS 1 MCAP "
        "(--record FILE.mcap's) with cps_web's player, in place of the simulator, on the recording's clock; "
        "the mission ends with the recording",
    )
    parser.add_argument(
        "--bandwidth-manager",
        choices=("on", "off"),
        default="on",
        help="off: no bandwidth manager; each robot's rate limiter passes its sensor's full rate and each "
        "camera sends its finest video at the fleet's maximum rate (the unmanaged case, for comparison)",
    )
    parser.add_argument(
        "--select-robot",
        default=None,
        metavar="ROBOT",
        help="the camera robot whose video the operator watches from the start (the GUI's choice replaces it): "
        "the manager gives it operator-quality video first",
    )
    parser.add_argument(
        "--tissue-layout",
        choices=TISSUE_LAYOUTS,
        default=SHARED,
        help="shared: a fixed number of robots' tissue processes for any fleet (one nodelet "
        "manager and loader, one cloud_tissue; the twin's map server decodes what it inserts); "
        "per_robot: one process per node and robot, to compare with",
    )
    parser.add_argument(
        "--video-trace",
        default=None,
        metavar="PATH",
        help="the cameras play this recorded video (python -m cps_sim.video_trace record) at the level and "
        "rate they are allocated instead of rendering it: ~no CPU, the real frames' sizes (default: rendered live)",
    )
    parser.add_argument(
        "--kill-map-server-at",
        type=float,
        default=None,
        metavar="S",
        help="fault injection: kill the map server S seconds into the mission",
    )
    return parser


def mission_args(side, **options):
    """The parsed command line of `cps_bringup SIDE` with typed `options` in place of flags, for
    callers in Python (demo, monitor): the parser's defaults, no argv strings built and parsed back."""
    args = build_parser().parse_args([side])
    unknown = sorted(set(options) - set(vars(args)))
    if unknown:
        raise TypeError(f"unknown mission option(s): {', '.join(unknown)}")
    for key, value in options.items():
        setattr(args, key, value)
    return args


def _sides(side):
    return (PHYSICAL, DIGITAL) if side == "all" else (side,)


# What one mission's side writes into the output folder (the demo's report included). A new mission
# starts without them: the map server would otherwise resume from an earlier mission's map, and the
# CSVs (appended to, so that a restarted node keeps its rows) would mix two missions (link_thesis's
# reused folders held two missions' link_estimate.csv rows, under the older header, till 2026-11-30).
# test_supervisor checks this against every file the plan puts in the folder.
MISSION_OUTPUTS = {
    PHYSICAL: ("physical_stats.csv", "physical_arrivals.csv", "physical_counters.csv"),
    DIGITAL: (
        "map.bt",
        "map.bt.json",
        "map_changes.md",
        "map_changes.json",
        "stats.csv",
        "arrivals.csv",
        "counters.csv",
        "allocation.csv",
        "link_estimate.csv",
        "setpoints.csv",
        "gui.png",
        WEB_URL_FILE,
        "ground_truth.npz",
        "scores.json",
        "topdown.png",
        "link.png",
        "report.md",
        "link_events.csv",
        "link_state.csv",
        "trajectories.csv",
        "map_age.csv",
        "verdict.json",
    ),
}


def clear_previous_mission(out_dir, sides):
    """Remove what an earlier mission of these sides left in out_dir; returns the names removed."""
    removed = []
    for side in sides:
        for name in MISSION_OUTPUTS[side]:
            path = os.path.join(out_dir, name)
            if os.path.isfile(path):
                os.remove(path)
                removed.append(name)
    return removed


def _checked_web_listen(text):
    """--web-listen as host:port, or BringupError before anything starts."""
    from cps_web.endpoint import parse_listen

    try:
        parse_listen(text)
    except ValueError as exc:
        raise BringupError(f"--web-listen: {exc}") from exc
    return text


def _checked_link_addresses(args):
    """Split across machines each side names both listeners (the twin's main lane, the robots'
    command lane), or BringupError before anything starts."""
    twin, robots = getattr(args, "twin_address", None), getattr(args, "robots_address", None)
    if bool(twin) != bool(robots):
        raise BringupError(
            "--twin-address and --robots-address go together: the twin's bridge listens at the first "
            "(main lane), the robots' at the second (command lane)"
        )


def _checked_record_link_only(args, sides):
    """--record-link-only needs --record and the twin's side (what arrives there is what it records)."""
    if not getattr(args, "record_link_only", False):
        return False
    if not args.record:
        raise BringupError("--record-link-only: give the file with --record FILE.mcap (or a .bag)")
    if DIGITAL not in sides:
        raise BringupError("--record-link-only records what the twin receives: run the digital side here")
    return True


def _stop_on_signals():
    """SIGINT and SIGTERM end the mission as Ctrl-C does (the map saved, every node stopped). SIGINT
    explicitly: a process started in the background of a non-interactive shell inherits SIGINT
    ignored, and Python then keeps ignoring it (a chaos soak's bringup run that way did not stop on
    its harness's SIGINT and was killed 240 s later; rospy installs its own handler the same way)."""

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, handler)


def run_mission(args, log=print) -> MissionResult:
    """Bring up the chosen side(s), run until done/duration/Ctrl-C, save the map, stop everything."""
    try:
        fleet = load_fleet(args.fleet, profile=args.profile)
        fleet = robot_names_arg(fleet, args.robots.split(",") if args.robots else None)
    except (ConfigError, KeyError, ValueError) as exc:
        raise BringupError(str(exc).strip('"')) from exc
    selected = getattr(args, "select_robot", None)
    if selected and selected not in [r.name for r in fleet.robots if r.has_depth_camera]:
        cameras = ", ".join(r.name for r in fleet.robots if r.has_depth_camera) or "none"
        raise BringupError(f"--select-robot {selected}: not a camera robot of this fleet (camera robots: {cameras})")
    out_dir = os.path.abspath(args.out)
    sides = _sides(args.side)
    split = _host_split(args, sides)  # refused here, before anything starts
    baseline, site_changes = check_monitoring_inputs(args, fleet, sides)
    replay_path, replayed = _checked_replay(args.replay, fleet, sides, log)
    video_trace, video_source = _checked_video_trace(
        getattr(args, "video_trace", None), fleet, sides, args, replay_path
    )
    announce = _checked_announce(args, sides)
    web_listen = _checked_web_listen(getattr(args, "web_listen", WEB_LISTEN))
    _checked_link_addresses(args)
    record_link_only = _checked_record_link_only(args, sides)
    os.makedirs(out_dir, exist_ok=True)
    removed = clear_previous_mission(out_dir, sides)
    if removed:
        log(
            f"[bringup] {out_dir}: removed the previous mission's {', '.join(removed)} (a new mission starts "
            f"with an empty map)"
        )
    options = RunOptions(
        out_dir=out_dir,
        profile=args.profile,
        renderer=args.renderer,
        simulate=not args.no_sim,
        map_file=os.path.join(out_dir, "map.bt"),
        gui_screenshot_path=os.path.join(out_dir, "gui.png") if args.screenshot and DIGITAL in sides else None,
        gui_screenshot_after_s=args.screenshot_after,
        baseline_map=baseline,
        site_changes_file=site_changes,
        record_path=os.path.abspath(args.record) if args.record else None,
        replay_path=replay_path,
        bandwidth_manager=args.bandwidth_manager == "on",
        selected_robot=selected or "",
        control_layout=args.control_layout,
        tissue_layout=args.tissue_layout,
        video_trace=video_trace,
        web=getattr(args, "web", "on") == "on",
        web_listen=web_listen,
        record_link_only=record_link_only,
    )
    transport = args.transport
    if replay_path and transport == ZENOH and len(sides) == 2:
        log("[bringup] --replay: one master for both sides (tcpros), so that the bag's /clock reaches every node")
        transport = TCPROS
    zenoh = transport == ZENOH
    with contextlib.ExitStack() as stack:
        stack.callback(_kill_leftovers, out_dir, log)  # runs last, after every side has stopped
        try:
            stack.enter_context(split)
        except HostSplitError as exc:
            raise BringupError(str(exc)) from exc
        log(f"[bringup] {split.describe()}")
        log(f"[bringup] video: {video_source}")
        link = stack.enter_context(_link_context(args.link, log, getattr(args, "link_scenario", None), args.link_name))
        if link:
            # As the paper: the manager's B is what iperf3 measured on the link, not the nominal rate.
            options = dataclasses.replace(options, available_mbps=link.measured_mbps)
        if zenoh:
            options = dataclasses.replace(
                options,
                transport=ZENOH,
                twin_address=args.twin_address or (link.twin_ip if link else "127.0.0.1"),
                robots_address=args.robots_address or (link.phys_ip if link else "127.0.0.1"),
                zenoh_port=None if link or args.twin_address else free_port(),
                zenoh_command_port=None if link or args.robots_address else free_port(),
            )
            if link:  # after iperf3: from now on each host answers only at its bridge listener
                link.guard(_link_ports(options))
        specs = plan_nodes(fleet, sides=sides, options=options)
        if DIGITAL in sides:
            ensure_map_kernels(log)  # before the mission: no node compiles during it
        # Across machines the nodes must advertise this host's address: ROS_IP as the user set it.
        # Over Zenoh each side's graph stays on its host's loopback: only the bridge is on the link.
        host_ip = "127.0.0.1" if zenoh else link.twin_ip if link else (os.environ.get("ROS_IP") or "127.0.0.1")
        side_graphs = {}
        if zenoh and len(sides) == 2:
            side_graphs[PHYSICAL] = _robots_graph(out_dir, link)
            stack.callback(side_graphs[PHYSICAL].close)
            side_graphs[PHYSICAL].start()
        if args.master_uri:
            graph = RosGraph(master_uri=args.master_uri, log_dir=node_log_dir(out_dir), host_ip=host_ip)
        else:
            if args.port:
                ensure_port_free(args.port)
            graph = RosGraph(port=args.port, log_dir=node_log_dir(out_dir), host_ip=host_ip)
        stack.callback(graph.close)
        user = node_user(args.run_as)
        # Over Zenoh each side's nodes stay on their host's loopback; over TCPROS they advertise the link's addresses.
        side_env = {PHYSICAL: {"ROS_IP": link.phys_ip}, DIGITAL: {"ROS_IP": link.twin_ip}} if link and not zenoh else {}
        if user:
            ros_log_dir = os.path.join(node_log_dir(out_dir), "log")
            side_env = {side: {**side_env.get(side, {}), **user_env(ros_log_dir)} for side in sides}
            if zenoh:
                # The bridges run as `user` too: they get their own copy of the fleet's certificates.
                options = dataclasses.replace(options, cert_dir=_bridge_certs(os.path.join(ros_log_dir, "certs")))
                specs = plan_nodes(fleet, sides=sides, options=options)
            try:
                hand_over(user, out_dir, ros_log_dir)
                check_code_readable(user, specs)
                prefix = user_prefix(user)
            except PrivilegeError as exc:
                raise BringupError(str(exc)) from exc
            log(f"[bringup] the nodes run as '{user}' (root only for the link)")
        graph.start()
        if replay_path:
            # Every node (started after this) runs on the bag's clock, which rosbag play --clock publishes.
            import rosgraph

            rosgraph.Master("cps_bringup", master_uri=graph.uri).setParam(names.USE_SIM_TIME, True)
        robots_master = f"; robots master {side_graphs[PHYSICAL].uri} (joined by Zenoh bridges)" if side_graphs else ""
        log(
            f"[bringup] master {graph.uri}{robots_master}; "
            f"link: {link.describe() if link else 'loopback (no shaping)'}; "
            f"robots {', '.join(fleet.robot_names)}; profile {options.profile or fleet.profile.name}; out {out_dir}"
        )
        supervisor = Supervisor(
            specs,
            graph,
            log=log,
            side_prefix={PHYSICAL: link.exec_prefix("phys")} if link else None,
            side_env=side_env or None,
            side_graphs=side_graphs,
            policy=RestartPolicy.from_limits(fleet.limits),
            node_log_max_bytes=int(fleet.limits.node_log_max_mbytes * 1e6),
            user_prefix=prefix if user else None,
            spec_prefix=lambda spec: split.prefix(spec.side, tier=spec.tier),
            warm_spares=fleet.limits.warm_spares,
        )
        recorder_log = None
        if options.record_path:
            # Registered first, so it runs after stop_all: the recorder has closed (or died) by then.
            stack.callback(_finish_recording, options.record_path, lambda: recorder_log, log)
        stack.callback(supervisor.stop_all)
        import rospy

        graph.point_this_process_here()
        rospy.init_node("cps_bringup", anonymous=True, disable_signals=True)
        from cps_sim.estop_keeper import EstopKeeper

        stack.callback(EstopKeeper().close)  # the e-stop state outlives the GUI
        if replay_starts_paused(options, sides):
            # beside the start: the nodes that wait for the replay's first clouds hold start_all up
            import threading

            from cps_bringup.mission_bag import replay_topics

            threading.Thread(
                target=_play_once_recorded,
                # the topics the player advertises: those of the bag it plays
                args=([t for t in replay_topics(fleet) if t in replayed.topics], args.start_timeout, log),
                name="play_once_recorded",
                daemon=True,
            ).start()
        supervisor.start_all(timeout_s=args.start_timeout)
        if DIGITAL in sides:
            _record_map_server_ready(supervisor)
        recorder_log = supervisor.log_of(RECORDER)
        if link and DIGITAL in sides:
            from cps_bringup.link import CapacityAnnouncer

            # the true capacity always goes to the oracle topic; to the manager only when announced
            announcer = CapacityAnnouncer(link, log, to_manager=announce)
        else:
            announcer = None
        runner = (
            link.start_scenario(os.path.join(out_dir, "link_events.csv"), log, on_rate=announcer and announcer.on_rate)
            if link
            else None
        )
        if announcer and not runner:
            announcer.announce_fixed_rate()
        if runner:
            stack.callback(runner.stop)
        monitor = MissionMonitor(
            fleet, map_age_csv_path=os.path.join(out_dir, "map_age.csv") if DIGITAL in sides else None
        )
        stack.callback(monitor.close)

        killed = []

        def fault_injection(elapsed):
            if args.kill_map_server_at is not None and not killed and elapsed >= args.kill_map_server_at:
                os.kill(supervisor.pid_of("map_server"), signal.SIGKILL)
                supervisor.record(
                    "map_server", f"killed by --kill-map-server-at (fault injection, {elapsed:.0f} s into the mission)"
                )
                killed.append(elapsed)

        ended_by, elapsed = "interrupted", 0.0
        try:
            ended_by, elapsed = wait_for_mission(
                monitor,
                supervisor,
                args.duration,
                log=log,
                on_tick=fault_injection,
                finished=_replay_finished(supervisor, replayed.end_s) if replay_path else None,
            )
        except KeyboardInterrupt:
            log("[bringup] interrupted; shutting down")
        except MasterLost as exc:
            ended_by = MASTER_LOST
            supervisor.record("roscore", f"{exc}: the nodes cannot reach each other any more; ending the mission")
        if options.record_path:
            # The recording is the mission's: it ends with it, not after the map save and the screenshot.
            supervisor.stop(RECORDER)
        if ended_by == MASTER_LOST:
            map_file = _save_map_without_master(supervisor, options.map_file, log) if DIGITAL in sides else None
        else:
            map_file = _save_map(options.map_file, log) if DIGITAL in sides else None
        if options.gui_screenshot_path and ended_by != MASTER_LOST:
            _wait_for_screenshot(supervisor, options.gui_screenshot_path, log)
        return MissionResult(
            out_dir,
            ended_by,
            elapsed,
            link.describe() if link else "loopback",
            map_file,
            monitor.snapshot(),
            list(supervisor.events),
            supervisor.restarts(),
            split.describe(),
            video_source,
            announcer.describe() if announce else _unannounced(link, options, fleet),
        )


def _record_map_server_ready(supervisor):
    """Note when the clouds started and what the map server said when it became ready (its
    latched ~ready: kernels loaded, warm-up insertion done)."""
    import rospy
    from diagnostic_msgs.msg import DiagnosticStatus

    try:
        ready = rospy.wait_for_message(MAP_SERVER_READY, DiagnosticStatus, timeout=5.0).message
    except rospy.ROSException:
        ready = f"no message on {MAP_SERVER_READY}"
    sim = supervisor.running.get("fleet_sim")
    clouds = (
        f"fleet_sim (the clouds) started {sim.waited_s:.1f} s into the bring-up, after it"
        if sim and MAP_SERVER in sim.spec.after
        else "the clouds do not wait for it"
    )
    supervisor.record(MAP_SERVER, f"{ready}; {clouds}")


def _finish_recording(path, recorder_log, log):
    """The mission's bag in place once the recorder has stopped (reindexed if it was left open), else
    BringupError: a mission asked to record must not end quietly without its bag."""
    from cps_bringup.mission_bag import BagError, finish_recording

    try:
        log(f"[bringup] {finish_recording(path, recorder_log())}")
    except BagError as exc:
        raise BringupError(f"--record: {exc}") from exc


def _bridge_certs(folder):
    """A private copy of the fleet's CA and bridge certificates in `folder` (made on first use)."""
    import shutil

    from cps_link.zenoh_session import BridgeSetupError, default_cert_dir, ensure_certs

    try:
        source = ensure_certs(default_cert_dir())
    except BridgeSetupError as exc:
        raise BringupError(str(exc)) from exc
    os.makedirs(folder, mode=0o700, exist_ok=True)
    for name in ("ca.pem", "robots.pem", "robots.key", "twin.pem", "twin.key"):
        shutil.copy2(os.path.join(source, name), os.path.join(folder, name))
    return folder


def check_monitoring_inputs(args, fleet, sides):
    """(baseline path, changes path), absolute, after checking them before anything starts: BringupError
    for a baseline that is missing, corrupt or of another resolution or frame, a changes file that does
    not fit the site (file:line), or changes without a baseline."""
    from cps_mapping.baseline import BaselineError, load_baseline

    baseline = os.path.abspath(os.path.expanduser(args.baseline)) if args.baseline else None
    changes = os.path.abspath(os.path.expanduser(args.site_changes)) if args.site_changes else None
    if changes and not baseline:
        raise BringupError(
            "--site-changes makes this a monitoring mission, which needs --baseline MAP.bt "
            "(the map of an earlier mission, e.g. out/demo/map.bt from `make demo`)"
        )
    if baseline and baseline == os.path.join(os.path.abspath(args.out), "map.bt"):
        raise BringupError(
            f"--baseline {baseline} is this mission's own map file, which a new mission replaces; "
            f"copy it elsewhere or choose another --out"
        )
    if baseline and DIGITAL in sides:
        try:
            load_baseline(baseline, fleet.mapping)
        except BaselineError as exc:
            raise BringupError(f"--baseline: {exc}") from exc
    if changes and PHYSICAL in sides:
        from cps_fleet.site import load_site
        from cps_sim.site_changes import load_site_changes

        try:
            load_site_changes(changes, load_site(fleet.site_path))
        except ConfigError as exc:
            raise BringupError(f"--site-changes: {exc}") from exc
    return baseline, changes


def _checked_announce(args, sides):
    """True for --announce-link-capacity on a run that can honour it; BringupError, before anything
    starts, when there is no tc link to announce or the manager's side is not run here."""
    if not getattr(args, "announce_link_capacity", False):
        return False
    if args.link in (None, "", "none") and not getattr(args, "link_scenario", None):
        raise BringupError(
            "--announce-link-capacity announces the tc link's rate: use it with --link RATE or --link-scenario NAME"
        )
    if DIGITAL not in sides:
        raise BringupError(
            "--announce-link-capacity publishes on the twin's master, where the bandwidth manager runs: "
            "use it with `all` or `digital`"
        )
    return True


def _unannounced(link, options, fleet):
    """What the manager's budget was made from when no capacity was announced."""
    if not options.bandwidth_manager:
        return "not announced (no bandwidth manager)"
    start = f"iperf3's {link.measured_mbps:.1f} Mbit/s at the start" if link else "the configured capacity"
    if fleet.link.estimate_bandwidth and options.transport == ZENOH:
        return f"not announced: the manager's online estimate from the bridges' link reports, seeded by {start}"
    return f"not announced: the manager's budget from {start}"


def _checked_video_trace(path, fleet, sides, args, replay_path):
    """(absolute trace path or None, what the cameras' video is) for --video-trace: BringupError,
    before anything starts, for a trace that cannot feed the fleet's cameras or a run without them."""
    not_simulated = (
        "the robots' side's (not started here)"
        if PHYSICAL not in sides
        else "the real robots' cameras (--no-sim)"
        if args.no_sim
        else f"the replayed bag's ({replay_path})"
        if replay_path
        else None
    )
    if not path:
        return None, not_simulated or "rendered live by the simulated cameras at the allocated level and rate"
    if not_simulated:
        raise BringupError(
            "--video-trace feeds the simulated cameras: use it with `physical` or `all`, without --no-sim or --replay"
        )
    from cps_sim.video_trace import VideoTraceError, load_video_trace

    try:
        trace = load_video_trace(os.path.abspath(path), fleet)
    except VideoTraceError as exc:
        raise BringupError(f"--video-trace: {exc}") from exc
    return trace.path, trace.describe()


def _checked_replay(path, fleet, sides, log):
    """The absolute path of a bag or ROS 1 MCAP that can feed `fleet` and what it holds
    (mission_bag.BagContents), or BringupError saying why not; (None, None) without one."""
    if not path:
        return None, None
    if PHYSICAL not in sides:
        raise BringupError("--replay plays the robots' side: use it with `physical` or `all`")
    from cps_bringup.mission_bag import BagError, check_bag

    try:
        contents = check_bag(os.path.abspath(path), fleet)
    except BagError as exc:
        raise BringupError(str(exc)) from exc
    log(f"[bringup] replaying {path}: {contents.duration_s:.1f} s, {len(contents.topics)} topics")
    return os.path.abspath(path), contents


# After the bag ends, s for the tissue, the map server and a recorder to take in the last messages
# (the player, kept alive, still sends what it queued for them).
REPLAY_DRAIN_S = 3.0


# How long the paused player waits for the recorder to connect to its topics before playing anyway, s.
RECORDER_CONNECT_TIMEOUT_S = 30.0


def _play_once_recorded(topics, start_timeout_s, log):
    """Play the paused replay (rosbag play --pause) once the mission's recorder is connected to every
    topic it plays: what is published before a subscriber's connection is lost to it (a full run's
    MCAP of a replay lacked /scout/odom's first 2 messages, the recorder connected after the
    player's 2 s delay). Runs beside the start (the player starts last, within `start_timeout_s`);
    RECORDER_CONNECT_TIMEOUT_S after the player registered it plays anyway and says which topics
    had no recorder."""
    import rospy
    from std_srvs.srv import SetBool

    from cps_bringup.plan import REPLAY
    from cps_ros.processes import subscribers_of

    replay, recorder = names.absolute(REPLAY), names.absolute(RECORDER)
    service = f"{replay}/{names.PAUSE_PLAYBACK}"
    try:
        rospy.wait_for_service(service, timeout=start_timeout_s)
    except rospy.ROSException:
        log(f"[bringup] the replay's {service} did not come up: nothing to play")
        return
    deadline = time.monotonic() + RECORDER_CONNECT_TIMEOUT_S
    while True:
        connected = subscribers_of(replay, rospy.get_name())
        missing = [t for t in topics if recorder not in connected.get(t, ())]
        if not missing or time.monotonic() > deadline or rospy.is_shutdown():
            break
        time.sleep(0.1)
    if missing:
        log(
            f"[bringup] the recorder is not connected to {', '.join(missing)} after {RECORDER_CONNECT_TIMEOUT_S:g} s: playing anyway"
        )
    try:
        rospy.ServiceProxy(service, SetBool)(data=False)
    except (rospy.ServiceException, rospy.ROSException) as exc:
        log(f"[bringup] could not play the replay ({service}): {exc}")


def _replay_finished(supervisor, end_s):
    """The mission's end by its replay: the bag's clock passed `end_s` (its last message; the player
    runs on with -k) or the player ended; REPLAY_DRAIN_S later."""
    import rospy

    from cps_bringup.plan import REPLAY

    def finished():
        running = supervisor.running.get(REPLAY)
        ended = running is None or running.proc.poll() is not None
        # this process runs on /use_sim_time too (set before its init_node): the bag's clock
        if not ended and rospy.get_time() < end_s:
            return None
        time.sleep(REPLAY_DRAIN_S)
        return "replay"

    return finished


def _save_map(path, log):
    import rospy

    from cps_msgs.srv import SaveMap

    try:
        service = names.absolute(names.in_twin(names.SAVE_MAP))
        rospy.wait_for_service(service, timeout=10)
        reply = rospy.ServiceProxy(service, SaveMap)(path=path)
    except (rospy.ROSException, rospy.ServiceException) as exc:
        log(f"[bringup] could not save the map: {exc}")
        return None
    if not reply.success:
        log(f"[bringup] map server refused to save: {reply.message}")
        return None
    log(f"[bringup] map saved to {reply.path}")
    return reply.path


def _save_map_without_master(supervisor, path, log):
    """No master, no service: stop the map server with SIGINT; its shutdown hook saves to its map file."""
    before = os.path.getmtime(path) if os.path.exists(path) else None
    supervisor.stop("map_server", timeout_s=MAP_SAVE_ON_SHUTDOWN_TIMEOUT_S)
    if os.path.exists(path) and os.path.getmtime(path) != before:
        log(f"[bringup] map saved to {path} by the map server on shutdown")
        return path
    log(
        f"[bringup] the map server did not save on shutdown; {path} holds its last autosave"
        if os.path.exists(path)
        else "[bringup] no map saved"
    )
    return path if os.path.exists(path) else None


def _wait_for_screenshot(supervisor, path, log, timeout_s=90.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not os.path.exists(path):
        if "gui" in supervisor.running and supervisor.running["gui"].proc.poll() is not None:
            break
        time.sleep(0.5)
    log(f"[bringup] GUI screenshot {'saved to ' + path if os.path.exists(path) else 'missing'}")


def _robots_graph(out_dir, link):
    """The robots' own master (Zenoh, both sides in this run): on loopback, in the physical namespace
    with --link."""
    log_dir = os.path.join(node_log_dir(out_dir), "robots")
    os.makedirs(log_dir, exist_ok=True)
    graph = RosGraph(log_dir=log_dir, host_ip="127.0.0.1")
    if link:
        from cps_bringup.link import InNamespace

        return InNamespace(graph, link.netns_path("phys"))
    return graph


def _kill_leftovers(out_dir, log):
    """The guarantee that a mission leaves nothing running: after every side has stopped, a process
    still naming the mission folder (in its command line or environment) outlived its stop. It is
    killed, waited for, and named in the log, so that the leak stays visible."""
    from cps_ros.processes import kill_processes_named

    left = kill_processes_named(out_dir)
    if left:
        log(
            f"[bringup] WARNING: {len(left)} process(es) of this mission outlived their stop and were killed: "
            + "; ".join(f"{pid} {cmd[:160]}" for pid, cmd in left)
        )


def _host_split(args, sides):
    """The sides' CPU budgets: --host-cpus, else halves for a two-side --link run as root, else none.
    BringupError for a split the machine cannot honour."""
    from cps_bringup.host_split import (
        MISSION_SIDE_SHARES,
        HostSplit,
        default_host_cpus,
        parse_host_cpus,
        parse_host_quota,
    )

    text = getattr(args, "host_cpus", None)
    quota_text = getattr(args, "host_quota", None)
    linked = args.link not in (None, "", "none") or getattr(args, "link_scenario", None)
    try:
        if text == "none" or (text is None and not (linked and os.geteuid() == 0 and len(sides) == 2)):
            if quota_text:
                raise HostSplitError("--host-quota needs a host split (--host-cpus)")
            reason = "--host-cpus none" if text == "none" else "not asked (default only for --link runs as root)"
            return HostSplit({}, mode="none", reason=reason)
        cpus = parse_host_cpus(text) if text else default_host_cpus()
        quota = parse_host_quota(quota_text, cpus or {}) if quota_text else {}
        name = f"cpsfleet_{args.link_name}" if getattr(args, "link_name", None) else f"cpsfleet_{os.getpid()}"
        return HostSplit.choose(cpus, quota, name=name, shares=dict.fromkeys(cpus or {}, MISSION_SIDE_SHARES))
    except HostSplitError as exc:
        raise BringupError(str(exc)) from exc


def _link_ports(options):
    """Each host's bridge listeners, "phys" or "twin" -> ports (the options', else bridge.yaml's)."""
    from cps_link.bridge_config import load_bridge_table
    from cps_link.netns_link import host_of

    listening = load_bridge_table().listening_ports(options.zenoh_port, options.zenoh_command_port)
    return {host_of(side): ports for side, ports in listening.items()}


@contextlib.contextmanager
def _link_context(rate, log, scenario_name=None, name=None):
    if rate in (None, "", "none") and not scenario_name:
        yield None
        return
    from cps_bringup.link import namespaced_link
    from cps_link.netns_link import LinkError
    from cps_link.scenario import load_scenario

    try:
        scenario = load_scenario(scenario_name) if scenario_name else None
    except ConfigError as exc:
        raise BringupError(f"--link-scenario {scenario_name}: {exc}") from exc
    try:
        with namespaced_link(rate, log, scenario, name) as link:
            yield link
    except LinkError as exc:
        raise BringupError(f"--link {rate}: {exc}") from exc


def main(argv=None):
    args = build_parser().parse_args(argv)
    _stop_on_signals()
    try:
        result = run_mission(args)
    except BringupError as exc:
        print(f"cps_bringup: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    print(f"[bringup] ended by {result.ended_by} after {result.elapsed_s:.0f} s; outputs in {result.out_dir}")
    if result.ended_by == MASTER_LOST:
        print(
            f"cps_bringup: error: the ROS master died; mission ended (map: {result.map_file or 'none'})",
            file=sys.stderr,
        )
        return EXIT_MASTER_LOST
    return 0
