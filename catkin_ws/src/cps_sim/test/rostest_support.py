"""What the cps_sim ROS tests share: starting a robot's nodes, and tf read back as numbers."""

import math

from cps_fleet import names


def start_robot_nodes(ros, name, fleet_file=None):
    params = {"~robot": name, **({"~fleet_file": fleet_file} if fleet_file else {})}
    ros.start_node("cps_sim", "velocity_mux", name="velocity_mux", namespace=names.absolute(name), params=params)
    ros.start_node(
        "cps_sim", "route_controller", name="route_controller", namespace=names.absolute(name), params=params
    )


def quat_yaw(q):
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
