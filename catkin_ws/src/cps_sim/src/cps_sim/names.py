"""The topic and frame names cps_sim's nodes use, in one place.

velocity_mux and route_controller run in the robot's namespace (`/<r>`), so their names are
relative. fleet_sim serves every robot from one node in the root namespace and builds
`<r>/<topic>` with `robot_topic`. Either way the resolved names are the contract's
(`/<r>/odom`, `/<r>/cmd_vel`, ...). Site-wide topics are global.
"""
from cps_fleet.names import MAP_FRAME, base_frame, odom_frame, robot_topic  # noqa: F401 (shared per-robot names)

# Per robot, relative to the robot's namespace.
# The cloud topic is the robot type's (fleet.yaml robot_types[*].cloud_topic).
CAMERA_IMAGE = "camera/image_raw"
CAMERA_INFO = "camera/camera_info"
ODOM = "odom"
JOINT_STATES = "joint_states"
BATTERY = "battery"
CMD_VEL = "cmd_vel"
CMD_VEL_AUTO = "cmd_vel/auto"
CMD_VEL_TELEOP = "cmd_vel/teleop"
CONTROL_MODE = "control_mode"
CONTROL_MODE_ACTIVE = "control_mode/active"
MISSION_STATE = "mission_state"
FLIGHT_COMMAND = "flight_command"

# Site-wide.
ESTOP = "/fleet/estop"
DIAGNOSTICS = "/diagnostics"
