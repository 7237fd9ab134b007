"""The map server's topic and service names: relative to its namespace, private (~) where
octomap_server's are.

The server runs in `/twin` as `map_server` (plan.py, the launch files), so these resolve to
`/twin/octomap_binary`, `/twin/<r>/points`, `/twin/map_server/clear_bbx` and so on
(docs/ros-graph.md): octomap_server's names, so its users' remappings and tools apply.
"""
import re
from typing import Optional

OCTOMAP_BINARY = "octomap_binary"
OCTOMAP_FULL = "octomap_full"
OCCUPIED_CELLS = "occupied_cells_vis_array"
POINT_CLOUD_CENTERS = "octomap_point_cloud_centers"
PROJECTED_MAP = "projected_map"
MAP_STATS = "map_stats"
MAP_CHANGES = "map_changes"

SAVE_MAP = "save_map"
LOAD_MAP = "load_map"
RESET = "~reset"
CLEAR_BBX = "~clear_bbx"
# diagnostic_msgs/DiagnosticStatus, latched, advertised once the kernels are loaded and a warm-up
# insertion ran: the first cloud after it is inserted at full speed (bringup starts the clouds then).
READY = "~ready"


def robot_points(robot: str) -> str:
    """A robot's decoded cloud topic."""
    return f"{robot}/points"


def robot_backfill_points(robot: str) -> str:
    """A robot's decoded backfill keyframes: clouds captured while the link was down (cps_link)."""
    return f"{robot}/points_backfill"


def robot_backfill_pose(robot: str) -> str:
    """geometry_msgs/TransformStamped: the fixed frame <- sensor frame pose of each backfill keyframe,
    sent before it (it may be older than the tf buffer)."""
    return f"{robot}/points_backfill/pose"


def robot_of_points_topic(topic: str, namespace: str) -> Optional[str]:
    """The robot whose cloud topic the resolved name `topic` is, in `namespace`; None if it is none."""
    prefix = re.escape(namespace.rstrip("/") + "/")
    match = re.match(prefix + "([^/]+)" + re.escape(robot_points("")) + "$", topic)
    return match.group(1) if match else None

# cps_bw_manager's service, called for robots near a new change.
SET_PRIORITY = "/tissue/set_priority"
