"""The ROS graph names contract, in code: every topic, service, node and frame name of the system.

`docs/ros-graph.md` is the contract; this module is its one home in code, imported by every
package, `bench/` and the tests. Names are relative where a user would remap them: started in the
root namespace they resolve to the contract's names (`tissue/stats` -> `/tissue/stats`,
`robot_topic("scout", ODOM)` -> `/scout/odom`), started under `__ns:=` they move with the node.
Node ports a user remaps per node are private (`~input`). Only ROS's own global topics, the
site-wide e-stop (shared by nodes in every robot's namespace) and the sim-time parameter are
absolute. `absolute()` gives a fully qualified name for tools that need one (rviz configs,
rosbag, waits on the master's topic list).
"""

import re
from typing import List, Optional

# --- frames (REP 105) --------------------------------------------------------------------------
MAP_FRAME = "map"


def odom_frame(robot):
    return f"{robot}/odom"


def base_frame(robot):
    return f"{robot}/base_link"


# --- global: ROS's own, and what every namespace shares -----------------------------------------
TF = "/tf"
TF_STATIC = "/tf_static"
DIAGNOSTICS = "/diagnostics"
ROSOUT = "/rosout"
ROSOUT_AGG = "/rosout_agg"
ESTOP = "/fleet/estop"
USE_SIM_TIME = "/use_sim_time"
# rosbag play's own private service (std_srvs/SetBool: true pauses, false plays on)
PAUSE_PLAYBACK = "pause_playback"
# rospy reads it at every log line; every master we start sets it (cps_ros.processes.MASTER_DEFAULTS)
ROSOUT_DISABLE_TOPICS_GENERATION = "/rosout_disable_topics_generation"

# --- per robot, relative to the robot's namespace ------------------------------------------------
# The robot's raw cloud topic is its robot type's (fleet.yaml robot_types[*].cloud_topic).
ODOM = "odom"
JOINT_STATES = "joint_states"
BATTERY = "battery"
CAMERA_IMAGE = "camera/image_raw"
CAMERA_INFO = "camera/camera_info"
COMPRESSED_SUFFIX = "compressed"  # image_transport's compressed plugin: <image>/compressed
CAMERA_IMAGE_COMPRESSED = f"{CAMERA_IMAGE}/{COMPRESSED_SUFFIX}"
CMD_VEL = "cmd_vel"
CMD_VEL_AUTO = "cmd_vel/auto"
CMD_VEL_TELEOP = "cmd_vel/teleop"
CONTROL_MODE = "control_mode"
CONTROL_MODE_ACTIVE = "control_mode/active"
MISSION_STATE = "mission_state"
FLIGHT_COMMAND = "flight_command"
POINTS_FILTERED = "points_filtered"  # the voxel grid's output
POINTS_DRACO = "points_filtered/draco"  # the Draco encoder's output
POINTS_MANAGED = "points_filtered/draco/managed"  # the rate limiter's output: what crosses the link
CLOUD_THROTTLE = "cloud_throttle"  # the robot's rate limiter (node name in the robot's namespace)
LIMITER_RATE_HZ = f"{CLOUD_THROTTLE}/rate_hz"
LIMITER_STATUS = f"{CLOUD_THROTTLE}/status"
# std_msgs/UInt8, latched, from the manager: the cloud's level (index into fleet.yaml
# streams.cloud_levels) that the robot's voxel grid produces.
LIMITER_LEVEL = f"{CLOUD_THROTTLE}/level"
# The robot's video stream under the manager: its rate (std_msgs/Float64) and level (std_msgs/UInt8,
# index into streams.video_levels), both latched; the camera renders and encodes only that.
VIDEO_THROTTLE = "video_throttle"
VIDEO_RATE_HZ = f"{VIDEO_THROTTLE}/rate_hz"
VIDEO_LEVEL = f"{VIDEO_THROTTLE}/level"
VIDEO_STATUS = f"{VIDEO_THROTTLE}/status"
# Decoded clouds at the twin's map server, relative to the map server's namespace.
POINTS = "points"
POINTS_BACKFILL = "points_backfill"  # keyframes captured while the link was down (cps_link)
POINTS_BACKFILL_DRACO = "points_backfill/draco"  # the keyframes as the bridge relays them, still encoded
POINTS_BACKFILL_POSE = "points_backfill/pose"  # map <- sensor pose of each keyframe, sent before it

# --- a node's own ports (private) -----------------------------------------------------------------
INPUT = "~input"
OUTPUT = "~output"
STATUS = "~status"  # rate_limiter's state
SET_RATE = "~set_rate"
RATE_HZ = "~rate_hz"

# --- the digital tissue, relative to the root namespace -------------------------------------------
TISSUE_STATS = "tissue/stats"
PHYSICAL_STATS = "tissue/physical_stats"
ALLOCATION = "tissue/allocation"
AVAILABLE_BANDWIDTH = "tissue/available_bandwidth"
SET_PRIORITY = "tissue/set_priority"
# std_msgs/String, latched, from the operator GUI: the robot whose video the operator watches
# ("" for none). It and a robot in teleop get operator-quality video first.
SELECTED_ROBOT = "tissue/selected_robot"
LINK_STATE = "tissue/link_state"  # cps_msgs/LinkState, published by each side's bridge
# cps_msgs/LinkCapacity (latched): the link's capacity announced by who knows it (bringup's
# --announce-link-capacity: the tc scenario's rate steps); the manager's budget follows it.
LINK_CAPACITY = "tissue/link_capacity"
# cps_msgs/LinkReport, ~2 Hz, from the twin's bridge (main lane): one measurement interval of the
# link robots -> twin (delivered, sent, offered, app-limited, heartbeat RTTs, receiver behind); the
# bandwidth manager's estimator input (issue 35).
LINK_REPORT = "tissue/link_report"
# cps_msgs/LinkEstimate, from the bandwidth manager: its capacity estimate beside the true capacity
# (when the test bed says it) and their ratio, for the GUI and reports.
LINK_ESTIMATE = "tissue/link_estimate"
# cps_msgs/LinkCapacity (latched): the test bed's tc rate as it changes, an ORACLE for reports and
# the GUI only (bringup with a tc link); the manager labels its estimate with it, never allocates from it.
LINK_TRUE_CAPACITY = "tissue/link_true_capacity"
# TwistStamped probes sent twin -> robots in the bridge's command class (teleop's): their latency,
# measured on the robots' side, is the teleop command latency.
COMMAND_PROBE = "tissue/command_probe"
TISSUE_NODELET_MANAGER = "tissue_nodelet_manager"

# --- the digital twin -------------------------------------------------------------------------------
TWIN_NS = "twin"
MAP_SERVER = "map_server"
# The map server's names, relative to its namespace (octomap_server's names and private services).
OCTOMAP_BINARY = "octomap_binary"
OCTOMAP_FULL = "octomap_full"
OCCUPIED_CELLS = "occupied_cells_vis_array"
POINT_CLOUD_CENTERS = "octomap_point_cloud_centers"
PROJECTED_MAP = "projected_map"
MAP_STATS = "map_stats"
MAP_CHANGES = "map_changes"
INSERT_CAPACITY = "insert_capacity"  # cps_msgs/InsertCapacity: what the map server can insert
SAVE_MAP = "save_map"
LOAD_MAP = "load_map"
RESET = "~reset"
CLEAR_BBX = "~clear_bbx"
# diagnostic_msgs/DiagnosticStatus, latched, advertised once the kernels are loaded and a warm-up
# insertion ran: the first cloud after it is inserted at full speed (bringup starts the clouds then).
READY = "~ready"

# --- the twin's Foxglove endpoint (cps_web), relative to the twin's namespace -----------------------
# Its node, and its channels: Foxglove topics (not ROS topics) that a Foxglove or Lichtblick viewer
# subscribes over the endpoint's WebSocket, named like the ROS graph (`twin/web/map`).
FOXGLOVE_ENDPOINT = "foxglove_endpoint"
WEB_MAP = "web/map"  # foxglove.PointCloud: the fused map's occupied voxel centres
WEB_TF = "web/tf"  # foxglove.FrameTransforms: /tf and /tf_static
WEB_FLEET = "web/fleet"  # foxglove.SceneUpdate: each robot's pose (arrow) and trail, its GUI colour
WEB_CHANGES = "web/changes"  # foxglove.SceneUpdate: the change clusters, the GUI's colours
WEB_VIDEO = "web/video"  # foxglove.CompressedImage: the selected robot's managed video as it arrives
WEB_HEALTH = "web/health"  # JSON: per robot battery, mission state, control mode, pose age
WEB_LINK = "web/link"  # JSON: the link's budget, allocation and capacity (plots)
WEB_ENDPOINT = "web/endpoint"  # JSON: the endpoint's own counters (queued, dropped, converted)
# Its services (JSON): the operator's robot (as the GUI's /tissue/selected_robot) and a robot's
# priority (through /tissue/set_priority).
WEB_SELECT_ROBOT = "web/select_robot"
WEB_SET_PRIORITY = "web/set_priority"


def web_pose(robot):
    """The robot's pose channel (foxglove.PoseInFrame), relative to the twin's namespace."""
    return f"web/{robot}/pose"


def admission_node(map_server_name):
    """The map server's receive process, a node of its own beside it (`map_server` ->
    `map_server_input`): it subscribes the robots' managed clouds and tf (issue 37)."""
    return f"{map_server_name}_input"


def robot_topic(robot, name):
    """`name` in the robot's namespace, relative: `<robot>/<name>`."""
    return f"{robot}/{name}"


def in_twin(name):
    """A name of the twin's namespace as seen from the root namespace: `twin/<name>`."""
    return f"{TWIN_NS}/{name}"


def private(node, name):
    """The private `name` (`~name`) of the node `node`, as seen from where `node` is named:
    `private("map_server", READY)` -> `map_server/ready`."""
    return f"{node}/{name.lstrip('~')}"


def managed_cloud(robot):
    """The robot's managed cloud on the robots' side (what its rate limiter publishes)."""
    return robot_topic(robot, POINTS_MANAGED)


def managed_cloud_at_twin(robot):
    """The managed cloud as relayed on the twin's side (the link carries it once)."""
    return in_twin(managed_cloud(robot))


def twin_points(robot):
    """The robot's decoded cloud at the twin, from the root namespace."""
    return in_twin(robot_topic(robot, POINTS))


def light_robot_streams(robot) -> List[str]:
    """The robot's unmanaged streams that cross the link whole (the reserve)."""
    return [robot_topic(robot, t) for t in (ODOM, BATTERY, JOINT_STATES)]


def absolute(name, namespace="/"):
    """`name` fully qualified from `namespace` (private names are not resolved here)."""
    if name.startswith("/"):
        return name
    if name.startswith("~"):
        raise ValueError(f"'{name}' is private: resolve it with the node's name")
    return namespace.rstrip("/") + "/" + name


def robot_of_topic(topic: str, name: str, namespace: str = "/") -> Optional[str]:
    """The robot whose `name` the resolved `topic` is, in `namespace` (`/twin/scout/points` ->
    `scout`); None if it is nobody's."""
    prefix = re.escape(namespace.rstrip("/") + "/")
    match = re.match(prefix + "([^/]+)/" + re.escape(name) + "$", topic)
    return match.group(1) if match else None
