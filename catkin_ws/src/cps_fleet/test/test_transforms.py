"""Rigid transforms and a robot type's sensor mount and body in base_link (cps_fleet.transforms)."""

import math

import numpy as np
import pytest

from cps_fleet.fleet import load_fleet
from cps_fleet.transforms import body_in_base, pose_matrix, rigid_inverse, sensor_in_base


def test_rigid_inverse_undoes_a_pose():
    m = pose_matrix(1.0, -2.0, 0.5, 0.7, math.radians(20.0))
    np.testing.assert_allclose(rigid_inverse(m) @ m, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(rigid_inverse(m), np.linalg.inv(m), atol=1e-12)


@pytest.fixture(scope="module")
def types():
    return load_fleet().robot_types


def test_a_lidar_is_mounted_level_at_its_mount(types):
    np.testing.assert_allclose(sensor_in_base(types["wheeled_lidar"]), pose_matrix(0.0, 0.0, 0.55, 0.0), atol=1e-12)


def test_a_depth_cameras_optical_axis_looks_forward_and_down_by_its_pitch(types):
    m = sensor_in_base(types["aerial_depth"])
    np.testing.assert_allclose(m[:3, 3], (0.28, 0.0, 0.06))
    pitch = math.radians(45.0)
    np.testing.assert_allclose(m[:3, 2], (math.cos(pitch), 0.0, -math.sin(pitch)), atol=1e-12)  # optical z
    np.testing.assert_allclose(m[:3, 0], (0.0, -1.0, 0.0), atol=1e-12)  # optical x: the robot's right


def test_the_body_box_stands_upright_above_base_link(types):
    np.testing.assert_allclose(body_in_base(types["legged_depth"]), pose_matrix(0.0, 0.0, 0.32, 0.0))
