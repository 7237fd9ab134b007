"""How the bringup starts pcl_ros's pcl/VoxelGrid for one robot (ci/env.sh must be sourced so
pcl_ros's plugins load): its name, topics and parameters, for `nodelet load`/`standalone` argv
and for the one loader (`nodelet_loader`) that puts every robot's into one manager."""

from cps_fleet import names

VOXEL_NODELET_TYPE = "pcl/VoxelGrid"
VOXEL_NODE_NAME = "voxel_grid"


def voxel_nodelet_params(robot_config, leaf_size_m=None):
    """Private parameters: the leaf it starts at (`leaf_size_m`, default the robot's voxel_leaf_m
    from fleet.yaml; the bringup passes cloud_levels.initial_leaf_m, the level nearest it; the
    tissue changes it live through the nodelet's dynamic_reconfigure service when the manager
    publishes a level) and no field filter (pcl_ros otherwise keeps only z in [0, 1] m in some
    versions and drops everything beyond 1 m)."""
    return {
        "leaf_size": float(robot_config.voxel_leaf_m if leaf_size_m is None else leaf_size_m),
        "filter_field_name": "",
        "filter_limit_min": -1.0e6,
        "filter_limit_max": 1.0e6,
    }


def voxel_nodelet_name(robot_config, name=VOXEL_NODE_NAME):
    """/<r>/voxel_grid: the nodelet's name (its private parameters live under it)."""
    return names.absolute(names.robot_topic(robot_config.name, name))


def voxel_nodelet_remaps(robot_config):
    """{private name: topic}: the robot's cloud topic (fleet.yaml) -> /<r>/points_filtered."""
    robot = robot_config.name
    return {
        names.INPUT: names.absolute(names.robot_topic(robot, robot_config.cloud_topic)),
        names.OUTPUT: names.absolute(names.robot_topic(robot, names.POINTS_FILTERED)),
    }


def voxel_nodelet_args(robot_config, manager=None, name=VOXEL_NODE_NAME, leaf_size_m=None):
    """argv of `rosrun nodelet nodelet` running pcl/VoxelGrid as /<r>/<name>, /<r>/<cloud topic> ->
    /<r>/points_filtered, starting at `leaf_size_m` (see voxel_nodelet_params); standalone, or
    loaded into `manager` (a nodelet manager's name)."""
    robot = robot_config.name
    mode = ["load", VOXEL_NODELET_TYPE, manager] if manager else ["standalone", VOXEL_NODELET_TYPE]
    argv = ["rosrun", "nodelet", "nodelet", *mode, f"__name:={name}", f"__ns:=/{robot}"]
    argv += [f"{key}:={value}" for key, value in voxel_nodelet_remaps(robot_config).items()]
    for key, value in voxel_nodelet_params(robot_config, leaf_size_m).items():
        argv.append(f"_{key}:={value}")
    return argv
