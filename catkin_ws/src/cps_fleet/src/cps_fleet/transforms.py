"""4x4 rigid transforms (numpy), and a robot type's body and sensor mount as transforms in base_link.

Shared by the simulator (which mounts the sensor and moves the body) and the twin (which removes
the robots' bodies from its map) so that both place them alike from the fleet contract
(fleet.yaml robot_types: `body`, `sensor_mount`).
"""

import math

import numpy as np

# Optical frame (z forward, x right, y down) in a body-style sensor frame (x forward, z up), REP 103.
OPTICAL_IN_SENSOR = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def pose_matrix(x, y, z, yaw, pitch=0.0):
    """4x4 transform from yaw (about z) then pitch (about the new y), translation (x, y, z)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    m = np.eye(4)
    m[:3, :3] = np.array([[cy * cp, -sy, cy * sp], [sy * cp, cy, sy * sp], [-sp, 0.0, cp]])
    m[:3, 3] = (x, y, z)
    return m


def rigid_inverse(m):
    """The inverse of a 4x4 rigid transform (R^T, -R^T t): no LAPACK call, whose threads spun
    for milliseconds per call on a loaded machine (fleet_sim inverts one per robot per odom)."""
    out = np.eye(4)
    rotation_t = m[:3, :3].T
    out[:3, :3] = rotation_t
    out[:3, 3] = -rotation_t @ m[:3, 3]
    return out


def sensor_in_base(robot_type):
    """The static mount base_link -> the type's sensor frame (a cps_fleet RobotType): the lidar's
    frame, or a depth camera's optical frame."""
    mount = robot_type.sensor_mount
    sx, sy, sz = mount.xyz_m
    m = pose_matrix(sx, sy, sz, 0.0, math.radians(mount.pitch_deg))
    return m if robot_type.sensor == "lidar" else m @ OPTICAL_IN_SENSOR


def body_in_base(robot_type):
    """The body box's centre and axes in base_link (upright, `body.center_z_m` above it)."""
    return pose_matrix(0.0, 0.0, robot_type.body.center_z_m, 0.0)
