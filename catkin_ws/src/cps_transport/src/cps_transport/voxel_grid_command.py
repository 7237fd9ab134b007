"""How the bringup starts pcl_ros's pcl/VoxelGrid for one robot (ci/env.sh must be sourced so
pcl_ros's plugins load)."""


def voxel_nodelet_params(robot_config):
    """Private parameters: the robot's leaf size from fleet.yaml and no field filter (pcl_ros
    otherwise keeps only z in [0, 1] m in some versions and drops everything beyond 1 m)."""
    return {"leaf_size": float(robot_config.voxel_leaf_m), "filter_field_name": "",
            "filter_limit_min": -1.0e6, "filter_limit_max": 1.0e6}


def voxel_nodelet_args(robot_config, manager=None, name="voxel_grid"):
    """argv of `rosrun nodelet nodelet` running pcl/VoxelGrid as /<r>/<name>, /<r>/points ->
    /<r>/points_filtered; standalone, or loaded into `manager` (a nodelet manager's name)."""
    robot = robot_config.name
    mode = ["load", "pcl/VoxelGrid", manager] if manager else ["standalone", "pcl/VoxelGrid"]
    argv = ["rosrun", "nodelet", "nodelet", *mode, f"__name:={name}", f"__ns:=/{robot}",
            f"~input:=/{robot}/points", f"~output:=/{robot}/points_filtered"]
    for key, value in voxel_nodelet_params(robot_config).items():
        argv.append(f"_{key}:={value}")
    return argv
