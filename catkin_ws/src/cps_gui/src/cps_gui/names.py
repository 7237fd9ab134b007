"""The topic, service and frame names the operator GUI uses, in one place.

The GUI runs in the root namespace and serves every robot, so per-robot names are built relative
(`<r>/odom` resolves to `/<r>/odom`); the tissue's and the twin's names are relative too
(`tissue/stats` resolves to `/tissue/stats`), so `__ns:=` moves the GUI to a system started in a
namespace; the e-stop and ROS's own `/rosout_agg` stay global. rviz configs get fully qualified
names (`global_robot_topic`).
"""
from cps_fleet.names import MAP_FRAME, odom_frame, robot_topic  # noqa: F401 (the GUI's names, shared)

# Per robot.
ODOM = "odom"
BATTERY = "battery"
MISSION_STATE = "mission_state"
CONTROL_MODE = "control_mode"
CONTROL_MODE_ACTIVE = "control_mode/active"
CMD_VEL_TELEOP = "cmd_vel/teleop"
FLIGHT_COMMAND = "flight_command"

# Site-wide.
ESTOP = "/fleet/estop"
TISSUE_STATS = "tissue/stats"
ALLOCATION = "tissue/allocation"
AVAILABLE_BANDWIDTH = "tissue/available_bandwidth"
SET_PRIORITY = "tissue/set_priority"
LINK_STATE = "tissue/link_state"
MAP_STATS = "twin/map_stats"
PROJECTED_MAP = "twin/projected_map"
MAP_MARKERS = "twin/occupied_cells_vis_array"
MAP_CHANGES = "twin/map_changes"
ROSOUT = "/rosout_agg"


def global_robot_topic(robot, topic):
    return f"/{robot}/{topic}"


def twin_points(robot):
    """The robot's decoded cloud on the digital-twin side."""
    return f"/twin/{robot}/points"
