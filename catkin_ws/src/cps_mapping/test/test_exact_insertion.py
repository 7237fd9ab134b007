"""The fast insertion is OctoMap's own: on real cps_sim clouds it gives the finest-voxel log-odds
of plain sequential insertPointCloud (what octomap_server does per cloud), and keeps OctoMap's
max-range rule."""

import numpy as np
import pytest
from fleet_model import new_map, plain_tree

from cps_mapping.fused_map import _finest_voxels, pack_index

RES = 0.1


def _voxels(tree, resolution_m):
    index, values = _finest_voxels(tree, resolution_m)
    return dict(zip(pack_index(index).tolist(), values.tolist()))


@pytest.fixture(scope="module")
def sim_clouds():
    """Two robots' clouds from cps_sim, voxelized as the tissue does (depth 0.10 m, lidar 0.01 m)."""
    from sim_views import capture_views

    from cps_transport.voxel import voxel_downsample

    views = capture_views(
        {
            "jackal": [(-6.6, 1.8, 0.0, 35.0), (-6.5, 1.7, 0.0, 30.0), (-6.0, 0.0, 0.0, 0.0)],
            "scout": [(-6.5, -2.6, 0.0, 0.0), (-6.3, -2.6, 0.0, 10.0)],
        },
        robots=("jackal", "scout"),
    )
    leaf = {"jackal": 0.10, "scout": 0.01}
    max_range = {"jackal": 6.0, "scout": 12.0}
    return [
        (robot, np.asarray(voxel_downsample(points, leaf[robot]), dtype=np.float64), origin, max_range[robot])
        for robot in ("jackal", "scout")
        for points, origin in views[robot]
    ]


@pytest.mark.parametrize("resolution_m", [0.1, 0.05])
def test_insertion_equals_plain_sequential_octomap(sim_clouds, resolution_m):
    plain = plain_tree(resolution_m)
    fused = new_map(resolution_m)
    for robot, points, origin, max_range in sim_clouds:
        plain.insertPointCloud(points, origin, maxrange=max_range)
    jackal = [(p, o) for r, p, o, _ in sim_clouds if r == "jackal"]
    fused.insert_batch(jackal[:2], 6.0, "jackal")
    fused.insert_batch(jackal[2:], 6.0, "jackal")
    fused.insert_batch([(p, o) for r, p, o, _ in sim_clouds if r == "scout"], 12.0, "scout")
    expected, ours = _voxels(plain, resolution_m), _voxels(fused.tree, resolution_m)
    assert len(expected) > 10000
    assert set(ours) == set(expected), "the same voxels must be known (free or occupied)"
    keys = list(expected)
    difference = np.abs(np.array([ours[k] for k in keys]) - np.array([expected[k] for k in keys]))
    assert difference.max() < 1e-4
    occupied = {k for k, v in expected.items() if v > 0}
    assert set(pack_index(fused.occupied_index()).tolist()) == occupied
    assert sum(fused.contributions().values()) == len(occupied)


def test_max_range_point_clears_but_does_not_mark():
    fused = new_map(RES)
    origin = np.array([0.05, 0.05, 0.05])
    fused.insert_cloud(np.array([[20.05, 0.05, 0.05]]), origin, max_range_m=6.0)
    assert len(fused.occupied_index()) == 0, "a point beyond max range must not be marked"
    assert fused.is_free(np.array([[1.0, 0.05, 0.05], [5.8, 0.05, 0.05]])).all(), "it clears up to max range"
    assert not fused.is_free(np.array([[7.0, 0.05, 0.05], [20.05, 0.05, 0.05]])).any()
    plain = plain_tree(RES)
    plain.insertPointCloud(np.array([[20.05, 0.05, 0.05]]), origin, maxrange=6.0)
    assert _voxels(fused.tree, RES).keys() == _voxels(plain, RES).keys()


def test_an_occupied_voxel_is_cleared_by_later_clouds_as_octomap_does():
    fused, plain = new_map(RES), plain_tree(RES)
    origin = np.array([0.05, 0.05, 0.05])
    wall, far_wall = np.array([[2.05, 0.05, 0.05]]), np.array([[4.05, 0.05, 0.05]])
    for cloud in [wall] + [far_wall] * 3:
        fused.insert_cloud(cloud, origin, max_range_m=6.0)
        plain.insertPointCloud(cloud, origin, maxrange=6.0)
    ours, expected = _voxels(fused.tree, RES), _voxels(plain, RES)
    assert ours.keys() == expected.keys()
    assert max(abs(ours[k] - expected[k]) for k in expected) < 1e-4
    assert len(fused.occupied_index()) == 1 and fused.occupied_centers()[0][0] == pytest.approx(4.05)
