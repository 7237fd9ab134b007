"""Which processes each side of the system runs, with which names, remappings and parameters.

A pure function of the fleet configuration: `plan_nodes` returns `NodeSpec`s that the supervisor
starts and a launch-file writer could print. Topic names follow docs/ros-graph.md.
"""

import dataclasses
import os
import posixpath
import sys
from typing import Callable, Dict, List, Optional, Tuple

from cps_fleet import names
from cps_fleet.fleet import FleetConfig
from cps_sim.renderers import DEFAULT_RENDERER

PHYSICAL, DIGITAL = "physical", "digital"
# Scheduling tiers of a side's nodes when the sides are split (their nice: host_split.TIER_NICE):
# control (velocity mux, route control, fleet control, each side's command-lane bridge) above the
# map server (what keeps the operator's map fresh) above every other node of the side.
CONTROL_TIER, MAP_TIER, NORMAL_TIER = "control", "map", "normal"
TCPROS, ZENOH = "tcpros", "zenoh"
TRANSPORTS = (ZENOH, TCPROS)
SIDES = (PHYSICAL, DIGITAL)
# The robots' control (velocity mux + route controller): one fleet_control process for the fleet,
# or the single-robot velocity_mux and route_controller per robot (two processes per robot).
SHARED_CONTROL, PER_ROBOT_CONTROL = "shared", "per_robot"
CONTROL_LAYOUTS = (SHARED_CONTROL, PER_ROBOT_CONTROL)
FLEET_CONTROL = "fleet_control"
VOXEL_MANAGER = names.absolute(names.TISSUE_NODELET_MANAGER)
# The robots' tissue processes: "shared", a fixed number whatever the fleet's size (one nodelet
# manager + one loader for every robot's voxel grid, one cloud_tissue); or "per_robot", one process
# per node and robot (nodelet load, draco_encoder, rate_limiter), kept to compare with. The twin has
# no decoder process: the map server takes the managed clouds as the link delivers them and decodes
# only those it inserts (issue 37). The camera robots' JPEG video is the simulated camera's own, at
# the bandwidth manager's level and rate (cps_sim.video): no compressor process.
SHARED, PER_ROBOT = "shared", "per_robot"
TISSUE_LAYOUTS = (SHARED, PER_ROBOT)


@dataclasses.dataclass(frozen=True)
class NodeSpec:
    """One process of the running system."""

    label: str  # unique, e.g. "scout/draco_encoder"
    side: str
    argv: Tuple[str, ...]
    # Topics that must be advertised before the node counts as up.
    wait_topics: Tuple[str, ...] = ()
    # How often the supervisor restarts it when it dies (0: a death ends the run).
    restart_limit: int = 3
    # Labels of nodes that must be up before this one starts.
    after: Tuple[str, ...] = ()
    # A job that ends by itself (e.g. the GUI taking a screenshot): exit 0 is success, not a death.
    one_shot: bool = False
    # False: its exit, whatever the code, is noted and the mission goes on (the GUI).
    essential: bool = True
    # How long stopping may take before SIGTERM/SIGKILL (rosbag record writes out its queue).
    stop_timeout_s: float = 6.0
    # Its scheduling tier (CONTROL_TIER, MAP_TIER or NORMAL_TIER): above the sensors and clouds of
    # its side when the sides are split (host_split.TIER_NICE).
    tier: str = NORMAL_TIER
    # A Python node, (python, script, ...), whose restart the supervisor speeds up with a warm spare
    # (cps_ros.spare; fleet.yaml limits.warm_spares): the ones a map needs back within seconds.
    spare: bool = False


MAP_SERVER = names.MAP_SERVER
# Advertised (latched) by the map server once its kernels are loaded and a warm-up insertion ran.
MAP_SERVER_READY = names.absolute(names.in_twin(names.private(names.MAP_SERVER, names.READY)))

# The map server's live change report in the output folder (and its .json twin).
CHANGE_REPORT = "map_changes.md"

# The Foxglove endpoint's default address: the twin's host only (cps_web.endpoint), and the file in
# the output folder where it writes its ws:// URL once it listens.
WEB_LISTEN = "127.0.0.1:8765"
WEB_URL_FILE = "foxglove_url.txt"

# When the GUI screenshot is taken, s after the GUI starts: during the light profile's missions.
GUI_SCREENSHOT_AFTER_S = 35.0


@dataclasses.dataclass(frozen=True)
class RunOptions:
    out_dir: str
    profile: Optional[str] = None
    gui_screenshot_path: Optional[str] = None
    gui_screenshot_after_s: float = GUI_SCREENSHOT_AFTER_S
    map_file: Optional[str] = None
    renderer: str = DEFAULT_RENDERER
    # Link capacity for the bandwidth manager, Mbit/s (e.g. iperf3's measurement); None: fleet.yaml's.
    available_mbps: Optional[float] = None
    # False on real robots: their drivers publish what fleet_sim would.
    simulate: bool = True
    # A monitoring mission: the earlier map the twin compares with, and what the simulator changes.
    baseline_map: Optional[str] = None
    site_changes_file: Optional[str] = None
    # Record the mission to this rosbag (cps_bringup.mission_bag.record_topics).
    record_path: Optional[str] = None
    # Play this rosbag or ROS 1 MCAP in place of the robots (and the simulator), under its clock.
    replay_path: Optional[str] = None
    # "tcpros": one master across the link (the paper's set-up); "zenoh": a master per side joined
    # only by cps_link's bridges (the twin's main-lane bridge listens at twin_address:zenoh_port,
    # the robots' command-lane bridge at robots_address:zenoh_command_port).
    transport: str = TCPROS
    twin_address: str = "127.0.0.1"
    robots_address: str = "127.0.0.1"
    zenoh_port: Optional[int] = None
    # The command lane's port (None: bridge.yaml's command_port): each side runs its command-class
    # bridge as a process of its own, so teleop never waits behind clouds (cps_link LANES).
    zenoh_command_port: Optional[int] = None
    # The bridges' certificates (None: cps_link's default folder).
    cert_dir: Optional[str] = None
    # False: no bandwidth manager; every rate limiter passes the sensor's full rate (up to the
    # link's max_rate_hz), the paper's unmanaged case.
    bandwidth_manager: bool = True
    # The operator's robot from the start (the manager's ~selected_robot; the GUI's choice replaces it).
    selected_robot: str = ""
    # One of CONTROL_LAYOUTS.
    control_layout: str = SHARED_CONTROL
    # One of TISSUE_LAYOUTS.
    tissue_layout: str = SHARED
    # The cameras play this recorded video trace (cps_sim.video_trace) at the allocated level and
    # rate instead of rendering it; None: rendered live.
    video_trace: Optional[str] = None
    # The twin's Foxglove WebSocket endpoint (cps_web) and where it listens (host:port; port 0: any
    # free one, written to WEB_URL_FILE in the output folder).
    web: bool = True
    web_listen: str = WEB_LISTEN
    # Record only what crosses the link, as the twin receives it (cps_web.mcap_recording.link_topics).
    record_link_only: bool = False


A = names.absolute


def _rt(robot, name):
    """A robot's topic, fully qualified (the supervisor waits for it in the master's list)."""
    return A(names.robot_topic(robot, name))


def _tw(name):
    """A name in the twin's namespace, fully qualified."""
    return A(names.in_twin(name))


def _args(params: Dict[str, object]) -> List[str]:
    out = []
    for key, value in params.items():
        if isinstance(value, bool):
            value = "true" if value else "false"
        out.append(f"_{key}:={value}")
    return out


def _stats_topics(robots, video_robots=()):
    """What topic_stats measures on the twin: the relayed managed clouds and the light unmanaged
    streams (the same set as its fleet default, restricted to the running robots), and the managed
    video of `video_robots`."""
    topics = [A(t) for r in robots for t in (names.managed_cloud_at_twin(r), *names.light_robot_streams(r))]
    return ",".join(topics + _video_topics(video_robots) + [names.TF])


def _video_topics(video_robots):
    return [A(names.robot_topic(r, names.CAMERA_IMAGE_COMPRESSED)) for r in video_robots]


def default_node_path(package: str, node: str) -> str:
    """The node's executable as rospkg/catkin find it (devel or install space)."""
    from cps_ros.processes import find_node

    return find_node(package, node)


def plan_nodes(
    fleet: FleetConfig,
    sides=SIDES,
    options: RunOptions = None,
    node_path: Callable[[str, str], str] = default_node_path,
    python: str = sys.executable,
) -> List[NodeSpec]:
    """The processes of `sides` for `fleet` (its robots, its profile unless options.profile)."""
    options = options or RunOptions(out_dir=".")
    if options.tissue_layout not in TISSUE_LAYOUTS:
        raise ValueError(f"tissue_layout {options.tissue_layout!r}: one of {', '.join(TISSUE_LAYOUTS)}")
    robots = fleet.robot_names
    common = {"fleet_file": fleet.path}
    specs: List[NodeSpec] = []

    def py(package, node, *extra):
        return (python, node_path(package, node), *extra)

    def bridges(side, bridge_side):
        """The side's two bridge processes: the main lane (says whether the link is up) and the
        command lane (the command class alone, its own session and connection)."""
        from cps_link.zenoh_session import bridge_argv, bridge_node_name

        return [
            NodeSpec(
                bridge_node_name(bridge_side, lane),
                side,
                tuple(
                    bridge_argv(
                        python,
                        bridge_side,
                        options.twin_address,
                        robots,
                        cert_dir=options.cert_dir,
                        port=port,
                        fleet_file=fleet.path,
                        lane=lane,
                        robots_address=options.robots_address,
                    )
                ),
                wait_topics=(A(names.LINK_STATE),) if lane == "main" else (),
                # the command lane is teleop's path: above the clouds, like the mux
                tier=CONTROL_TIER if lane == "command" else NORMAL_TIER,
                spare=True,
            )
            for lane, port in (("main", options.zenoh_port), ("command", options.zenoh_command_port))
        ]

    if PHYSICAL in sides:
        profile = options.profile or fleet.profile.name
        if options.transport == ZENOH:
            specs += bridges(PHYSICAL, "robots")
        if options.simulate and not options.replay_path:
            specs.append(
                NodeSpec(
                    "fleet_sim",
                    PHYSICAL,
                    py(
                        "cps_sim",
                        "fleet_sim",
                        "__name:=fleet_sim",
                        *_args(
                            {
                                **common,
                                "profile": profile,
                                "robots": ",".join(robots),
                                "renderer": options.renderer,
                                "video_unmanaged": not options.bandwidth_manager,
                                **(
                                    {"site_changes_file": options.site_changes_file}
                                    if options.site_changes_file
                                    else {}
                                ),
                                **({"video_trace": options.video_trace} if options.video_trace else {}),
                            }
                        ),
                    ),
                    wait_topics=tuple(
                        t for r in fleet.robots for t in (_rt(r.name, names.ODOM), _rt(r.name, r.cloud_topic))
                    ),
                    restart_limit=0,
                    # The clouds start once the map server can insert them at full speed (MAP_SERVER_READY).
                    after=(MAP_SERVER,) if DIGITAL in sides else (),
                )
            )
        drivers = ("fleet_sim",) if options.simulate and not options.replay_path else ()
        simulated_camera = bool(drivers)  # fleet_sim's camera sends the managed video itself
        # Without the manager nothing lowers it: the sensors' full rate, up to the link's ceiling.
        initial_rate_hz = fleet.link.min_rate_hz if options.bandwidth_manager else fleet.link.max_rate_hz
        specs.append(
            NodeSpec(
                "nodelet_manager",
                PHYSICAL,
                ("rosrun", "nodelet", "nodelet", "manager", f"__name:={VOXEL_MANAGER.lstrip('/')}"),
                restart_limit=2,
            )
        )
        if options.control_layout not in CONTROL_LAYOUTS:
            raise ValueError(f"unknown control layout '{options.control_layout}' (known: {', '.join(CONTROL_LAYOUTS)})")
        if not options.replay_path and options.control_layout == SHARED_CONTROL:
            specs.append(
                NodeSpec(
                    FLEET_CONTROL,
                    PHYSICAL,
                    py(
                        "cps_sim",
                        "fleet_control",
                        f"__name:={FLEET_CONTROL}",
                        *_args({**common, "robots": ",".join(robots)}),
                    ),
                    wait_topics=tuple(_rt(r, t) for r in robots for t in (names.CMD_VEL, names.MISSION_STATE)),
                    after=drivers,
                    tier=CONTROL_TIER,
                )
            )
        for robot in fleet.robots:
            r = robot.name
            ns = f"__ns:={A(r)}"
            if not options.replay_path and options.control_layout == PER_ROBOT_CONTROL:  # replayed: not driven
                specs.append(
                    NodeSpec(
                        f"{r}/velocity_mux",
                        PHYSICAL,
                        py("cps_sim", "velocity_mux", ns, "__name:=velocity_mux", *_args({**common, "robot": r})),
                        wait_topics=(_rt(r, names.CMD_VEL),),
                        tier=CONTROL_TIER,
                    )
                )
                specs.append(
                    NodeSpec(
                        f"{r}/route_controller",
                        PHYSICAL,
                        py(
                            "cps_sim",
                            "route_controller",
                            ns,
                            "__name:=route_controller",
                            *_args({**common, "robot": r}),
                        ),
                        wait_topics=(_rt(r, names.MISSION_STATE),),
                        after=drivers,
                        tier=CONTROL_TIER,
                    )
                )
            if options.tissue_layout == PER_ROBOT:
                specs += _robot_tissue_per_robot(fleet, robot, py, initial_rate_hz)
            if robot.has_depth_camera and not simulated_camera:
                specs.append(_raw_camera_compressor(fleet, r, py))
        if options.tissue_layout != PER_ROBOT:
            specs += _robot_tissue_shared(fleet, py, initial_rate_hz)

        # The robots' side of the latency: capture stamp -> voxel-filtered cloud, measured on the
        # physical host (nothing crosses the link); the report joins its per-cloud arrivals with the
        # twin's by capture stamp. Also what the robots offer the link: each managed cloud and
        # camera video as the robots' side publishes it (local subscriptions, nothing crosses).
        specs.append(
            NodeSpec(
                "physical_stats",
                PHYSICAL,
                py(
                    "cps_transport",
                    "topic_stats",
                    "__name:=physical_stats",
                    f"{A(names.TISSUE_STATS)}:={A(names.PHYSICAL_STATS)}",
                    *_args(
                        {
                            **common,
                            "csv_path": os.path.join(options.out_dir, "physical_stats.csv"),
                            "arrivals_csv_path": os.path.join(options.out_dir, "physical_arrivals.csv"),
                            "counters_csv_path": os.path.join(options.out_dir, "physical_counters.csv"),
                            "arrival_topics": ",".join(
                                [_rt(r, names.POINTS_FILTERED) for r in robots] + [A(names.COMMAND_PROBE)]
                            ),
                            "topics": ",".join(
                                [_rt(r, names.POINTS_FILTERED) for r in robots]
                                + [A(names.COMMAND_PROBE)]
                                + [_rt(r, names.POINTS_MANAGED) for r in robots]
                                + _video_topics(r.name for r in fleet.robots if r.has_depth_camera)
                            ),
                        }
                    ),
                ),
                wait_topics=(A(names.PHYSICAL_STATS),),
            )
        )

    if DIGITAL in sides:
        out = options.out_dir
        if options.transport == ZENOH:
            specs += bridges(DIGITAL, "twin")
        for r in robots:
            # The one subscriber of the managed topic across the link; everything on the twin
            # (map server, statistics) reads the relay, so the link carries each cloud once. Over
            # Zenoh the twin's bridge publishes the relayed name itself.
            relayed = A(names.managed_cloud_at_twin(r))
            if options.transport == TCPROS:
                specs.append(
                    NodeSpec(
                        f"{r}/link_relay",
                        DIGITAL,
                        (
                            "rosrun",
                            "topic_tools",
                            "relay",
                            A(names.managed_cloud(r)),
                            relayed,
                            f"__ns:={A(names.in_twin(r))}",
                            "__name:=link_relay",
                        ),
                        wait_topics=(relayed,),
                    )
                )
        specs.append(
            NodeSpec(
                MAP_SERVER,
                DIGITAL,
                py(
                    "cps_mapping",
                    "map_server",
                    f"__ns:={A(names.TWIN_NS)}",
                    f"__name:={names.MAP_SERVER}",
                    *_args(
                        {
                            **common,
                            "robots": ",".join(robots),
                            "map_file": options.map_file or os.path.join(out, "map.bt"),
                            **(
                                {
                                    "baseline_map": options.baseline_map,
                                    "change_report": os.path.join(out, CHANGE_REPORT),
                                }
                                if options.baseline_map
                                else {}
                            ),
                        }
                    ),
                ),
                wait_topics=(_tw(names.MAP_STATS), _tw(names.OCTOMAP_BINARY), MAP_SERVER_READY),
                restart_limit=3,
                spare=True,
                tier=MAP_TIER,
            )
        )
        # The managed video, measured where it arrives: over Zenoh the twin's bridge republishes it
        # there; over one master a twin-side subscriber would pull a second copy across the link.
        measured_video = [r.name for r in fleet.robots if r.has_depth_camera] if options.transport == ZENOH else []
        specs.append(
            NodeSpec(
                "topic_stats",
                DIGITAL,
                py(
                    "cps_transport",
                    "topic_stats",
                    "__name:=tissue_stats",
                    *_args(
                        {
                            **common,
                            "csv_path": os.path.join(out, "stats.csv"),
                            "topics": _stats_topics(robots, measured_video),
                            "arrivals_csv_path": os.path.join(out, "arrivals.csv"),
                            "counters_csv_path": os.path.join(out, "counters.csv"),
                            "arrival_topics": ",".join(
                                [A(names.managed_cloud_at_twin(r)) for r in robots] + _video_topics(measured_video)
                            ),
                        }
                    ),
                ),
                wait_topics=(A(names.TISSUE_STATS),),
            )
        )
        specs.append(NodeSpec("command_probe", DIGITAL, py("cps_link", "command_probe", "__name:=command_probe")))
        if options.bandwidth_manager:
            specs.append(
                NodeSpec(
                    "bandwidth_manager",
                    DIGITAL,
                    py(
                        "cps_bw_manager",
                        "bandwidth_manager",
                        "__ns:=/",
                        "__name:=bandwidth_manager",
                        *_args(
                            {
                                **common,
                                "robots": ",".join(robots),
                                "csv_path": os.path.join(out, "allocation.csv"),
                                "link_state_csv_path": os.path.join(out, "link_state.csv"),
                                "link_estimate_csv_path": os.path.join(out, "link_estimate.csv"),
                                # over TCPROS no bridge reports the link: the configured capacity
                                **({"estimate_bandwidth": False} if options.transport == TCPROS else {}),
                                "setpoints_csv_path": os.path.join(out, "setpoints.csv"),
                                **({"selected_robot": options.selected_robot} if options.selected_robot else {}),
                                **(
                                    {"available_mbps": round(options.available_mbps, 2)}
                                    if options.available_mbps
                                    else {}
                                ),
                            }
                        ),
                    ),
                    wait_topics=(A(names.ALLOCATION),),
                )
            )
        if options.web:
            # A viewer's endpoint: its death is noted and the mission goes on, like the GUI's.
            specs.append(
                NodeSpec(
                    names.FOXGLOVE_ENDPOINT,
                    DIGITAL,
                    py(
                        "cps_web",
                        "foxglove_endpoint",
                        f"__ns:={A(names.TWIN_NS)}",
                        f"__name:={names.FOXGLOVE_ENDPOINT}",
                        *_args(
                            {
                                **common,
                                "robots": ",".join(robots),
                                "listen": options.web_listen,
                                "url_file": os.path.join(out, WEB_URL_FILE),
                            }
                        ),
                    ),
                    restart_limit=2,
                    essential=False,
                    after=(MAP_SERVER,),
                )
            )
        if options.gui_screenshot_path:
            # rviz needs an X server with OpenGL: a private Xvfb for the offscreen GUI (the host renders its
            # screenshot with Mesa's softpipe: cps_gui.host.choose_gl_driver).
            # xvfb-run is a shell that does not pass its own end on to the GUI: the GUI asks to be sent
            # SIGTERM when it ends, so that a killed bringup leaves no GUI behind.
            specs.append(
                NodeSpec(
                    "gui",
                    DIGITAL,
                    (
                        "env",
                        "QT_QPA_PLATFORM=xcb",
                        "xvfb-run",
                        "-a",
                        "-s",
                        "-screen 0 1920x1200x24",
                        "setpriv",
                        "--pdeathsig",
                        "TERM",
                        "--",
                        *py(
                            "cps_gui",
                            "cps_gui",
                            "--screenshot",
                            options.gui_screenshot_path,
                            "--after",
                            str(options.gui_screenshot_after_s),
                            "--fleet-file",
                            fleet.path,
                            "--robots",  # this mission's robots only (a monitoring mission sends back some)
                            ",".join(fleet.robot_names),
                        ),
                    ),
                    restart_limit=0,
                    one_shot=True,
                    essential=False,
                    after=("map_server",),
                )
            )
    specs += _bag_specs(fleet, sides, options, specs, py)
    return specs


def _robot_tissue_per_robot(fleet, robot, py, initial_rate_hz):
    """The per_robot layout: voxel grid (a `nodelet load` client), encoder, limiter and camera
    compressor of one robot, each its own process."""
    from cps_transport.cloud_levels import initial_leaf_m
    from cps_transport.voxel_grid_command import voxel_nodelet_args

    r, ns = robot.name, f"__ns:={A(robot.name)}"
    specs = [
        NodeSpec(
            f"{r}/voxel_grid",
            PHYSICAL,
            tuple(voxel_nodelet_args(robot, manager=VOXEL_MANAGER, leaf_size_m=initial_leaf_m(fleet, robot))),
            wait_topics=(_rt(r, names.POINTS_FILTERED),),
            after=("nodelet_manager",),
        ),
        NodeSpec(
            f"{r}/draco_encoder",
            PHYSICAL,
            py(
                "cps_transport",
                "draco_encoder",
                ns,
                "__name:=draco_encoder",
                f"{names.INPUT}:={_rt(r, names.POINTS_FILTERED)}",
                f"{names.OUTPUT}:={_rt(r, names.POINTS_DRACO)}",
                *_args({"cloud_levels": True}),
            ),
            wait_topics=(_rt(r, names.POINTS_DRACO),),
        ),
    ]
    specs.append(
        NodeSpec(
            f"{r}/cloud_throttle",
            PHYSICAL,
            py(
                "cps_transport",
                "rate_limiter",
                ns,
                f"__name:={names.CLOUD_THROTTLE}",
                f"{names.INPUT}:={_rt(r, names.POINTS_DRACO)}",
                f"{names.OUTPUT}:={_rt(r, names.POINTS_MANAGED)}",
                *_args({"rate_hz": initial_rate_hz, "cloud_levels": True}),
            ),
            wait_topics=(_rt(r, names.POINTS_MANAGED),),
        )
    )
    return specs


def _raw_camera_compressor(fleet, r, py):
    """Without the simulator's camera (a replayed bag, real robots) a depth robot's raw images
    become its managed video: shrunk to the manager's level and JPEG-encoded at its quality, at its
    rate, only while watched (the simulated camera renders and encodes its own instead)."""
    return NodeSpec(
        f"{r}/image_compressor",
        PHYSICAL,
        py(
            "cps_transport",
            "image_compressor",
            f"__ns:={_rt(r, posixpath.dirname(names.CAMERA_IMAGE))}",
            "__name:=image_compressor",
            *_args({"robot": r, "fleet_file": fleet.path}),
        ),
        wait_topics=(_rt(r, names.CAMERA_IMAGE_COMPRESSED),),
    )


def _robot_tissue_shared(fleet, py, initial_rate_hz):
    """The shared layout: one loader puts every robot's voxel grid into the nodelet manager, one
    cloud_tissue runs every robot's encoder and limiter (/<r>/cloud_throttle)."""
    robots = ",".join(fleet.robot_names)
    return [
        NodeSpec(
            "voxel_grid_loader",
            PHYSICAL,
            py(
                "cps_transport",
                "voxel_grid_loader",
                "__name:=voxel_grid_loader",
                *_args({"fleet_file": fleet.path, "robots": robots, "manager": VOXEL_MANAGER}),
            ),
            wait_topics=tuple(_rt(r, names.POINTS_FILTERED) for r in fleet.robot_names),
            after=("nodelet_manager",),
        ),
        NodeSpec(
            "cloud_tissue",
            PHYSICAL,
            py(
                "cps_transport",
                "cloud_tissue",
                "__name:=cloud_tissue",
                *_args(
                    {
                        "fleet_file": fleet.path,
                        "robots": robots,
                        "initial_rate_hz": initial_rate_hz,
                    }
                ),
            ),
            # Not the managed topics, advertised with the first cloud through: a replayed bag
            # starts once this process (every robot's encoder) is up.
            wait_topics=tuple(_rt(robot.name, names.POINTS_DRACO) for robot in fleet.robots),
            spare=True,
        ),
    ]


REPLAY, RECORDER = "mission_replay", "mission_recorder"


def _bag_specs(fleet, sides, options, planned, py):
    """The mission's recorder (rosbag record, or cps_web's MCAP recorder for a .mcap path) and the
    player of a recorded bag or MCAP (rosbag play, or cps_web's MCAP player; after everything else is up).

    A bag is LZ4-compressed: raw clouds are most of it, and a third of the bytes is less for a slow
    disk to take in before the recorder's stop timeout."""
    from cps_bringup.mission_bag import record_topics, replay_topics

    # The rate limiter and the link relay advertise the managed topics with the first cloud through.
    lazy = {A(t) for r in fleet.robot_names for t in (names.managed_cloud(r), names.managed_cloud_at_twin(r))}

    specs = []
    if options.record_path:
        if options.record_link_only:  # what the twin receives: recorded on its side
            from cps_web.mcap_recording import link_topics

            side = DIGITAL
            topics = link_topics(fleet.robot_names, [r.name for r in fleet.robots if r.has_depth_camera])
        else:
            side = PHYSICAL if PHYSICAL in sides else DIGITAL
            topics = record_topics(fleet)
        if is_mcap(options.record_path):
            argv = py(
                "cps_web",
                "mcap_recorder",
                f"__name:={RECORDER}",
                *_args({"path": options.record_path, "topics": ",".join(topics)}),
            )
        else:
            argv = ("rosbag", "record", "--lz4", "-O", options.record_path, f"__name:={RECORDER}", *topics)
        specs.append(NodeSpec(RECORDER, side, argv, restart_limit=0, stop_timeout_s=RECORDER_STOP_TIMEOUT_S))
    if options.replay_path and PHYSICAL in sides:
        from cps_bringup.mission_bag import is_mcap_recording

        # The player stays up after the last message (-k), its clock running on: a player that exits
        # drops what its publishers still queue for a slow subscriber (rosbag play shuts down at once;
        # the MCAP recorder of a replay in CI lacked 3 of 190 clouds and 18 of 766 joint states of one
        # robot). The mission ends the replay once the clock passed the recording's end
        # (cps_bringup.cli's REPLAY_DRAIN_S later).
        if is_mcap_recording(options.replay_path):  # cps_web's player: rosbag play's --clock, -d and -k, for MCAP
            params = {
                "path": options.replay_path,
                "topics": ",".join(replay_topics(fleet)),
                "delay_s": REPLAY_DELAY_S,
                "keep_alive": True,
            }
            argv = py("cps_web", "mcap_player", f"__name:={REPLAY}", *_args(params))
        else:  # --clock: every node runs on the bag's time (/use_sim_time); -d: subscribers connect first.
            # Recorded too: the player starts paused, and the mission plays it once the recorder is
            # connected to each of its topics (cps_bringup.cli): in a loaded full run the recorder's
            # connection to /scout/odom came after the 2 s delay, and the MCAP missed its first 2.
            paused = ("--pause",) if replay_starts_paused(options, sides) else ()
            argv = (
                "rosbag",
                "play",
                *paused,
                "--clock",
                "--keep-alive",
                "-d",
                str(REPLAY_DELAY_S),
                f"__name:={REPLAY}",
                options.replay_path,
                "--topics",
                *replay_topics(fleet),
            )
        specs.append(
            NodeSpec(
                REPLAY,
                PHYSICAL,
                argv,
                restart_limit=0,
                one_shot=True,
                after=tuple(s.label for s in planned + specs if not lazy & set(s.wait_topics)),
            )
        )
    return specs


def replay_starts_paused(options, sides) -> bool:
    """A ROS 1 bag replayed while the mission records starts paused (rosbag play --pause); the mission
    plays it once the recorder is connected to its topics (cps_bringup.cli)."""
    from cps_bringup.mission_bag import is_mcap_recording

    return bool(
        options.replay_path and options.record_path and PHYSICAL in sides and not is_mcap_recording(options.replay_path)
    )


def is_mcap(path: str) -> bool:
    """`--record FILE.mcap` records MCAP (cps_web's recorder); any other name a ROS 1 bag."""
    return path.lower().endswith(".mcap")


# rosbag record's buffer at the end of a mission: up to a few hundred MB to write out.
RECORDER_STOP_TIMEOUT_S = 60.0
# s between rosbag play advertising the topics and publishing the first message.
REPLAY_DELAY_S = 2.0
