"""Shared-origin casting (`exact_free_space=False`): every ray cast back from its endpoint,
stopping where its cloud already cleared. Approximate by design: it must keep >= 99 % of the
occupied voxels of exact insertion (OctoMap's) and never touch an endpoint's hit; the exact
mode must stay exact, and the .bt written from the grid must equal OctoMap's own writeBinary."""

import inspect

import numpy as np
import octomap
import pytest
import synthetic_scene as sc
from fleet_model import new_map, plain_tree

from cps_mapping.fused_map import FusedLogOddsMap, _finest_voxels, octree_from_bytes, pack_index

RES = 0.1
_STOP_DEFAULT_M = inspect.signature(FusedLogOddsMap).parameters["shared_ray_stop_m"].default


def _set(index):
    return set(pack_index(index).tolist())


@pytest.fixture(scope="module")
def clouds():
    """Two depth robots and a lidar robot crossing the synthetic hall, several frames each."""
    scene = sc.hall_scene()
    depth_a = sc.robot_clouds(scene, "depth", sc.trajectory([-1.0, 2.0, 0.5], [0.6, 2.4, 0.5], 5), RES)
    depth_b = sc.robot_clouds(scene, "depth", sc.trajectory([3.0, -3.0, 0.5], [2.0, -1.0, 0.5], 5), RES)
    lidar = sc.robot_clouds(scene, "lidar", sc.trajectory([-5.0, -1.5, 0.6], [-3.8, -1.0, 0.6], 3), 0.01)
    return [("a", depth_a, 6.0), ("b", depth_b, 6.0), ("l", lidar, 12.0)]


def _build(clouds, resolution_m, **kwargs):
    fused = new_map(resolution_m, **kwargs)
    for k in range(5):  # interleave the robots as a server would
        for robot, frames, max_range in clouds:
            if k < len(frames):
                fused.insert_batch(frames[k : k + 1], max_range, robot)
    return fused


@pytest.fixture(scope="module")
def built(clouds):
    """_build of `clouds`, once per set of arguments in this module: the tests only read the maps
    (the same map built again is the same map), and 11 builds were 7 different ones."""
    maps = {}
    defaults = {"exact_free_space": True, "shared_ray_stop_m": _STOP_DEFAULT_M}

    def get(resolution_m, **kwargs):
        key = (resolution_m, tuple(sorted({**defaults, **kwargs}.items())))
        if key not in maps:
            maps[key] = _build(clouds, resolution_m, **kwargs)
        return maps[key]

    return get


@pytest.mark.parametrize("resolution_m", [0.1, 0.05])
def test_shared_origin_casting_agrees_with_exact_insertion(built, resolution_m):
    exact = built(resolution_m)
    fast = built(resolution_m, exact_free_space=False)
    ours, theirs = _set(fast.occupied_index()), _set(exact.occupied_index())
    assert len(theirs) > 2000
    both = len(ours & theirs)
    assert both / len(theirs) >= 0.99 and both / len(ours) >= 0.99, (both / len(theirs), both / len(ours))
    assert fast._grid.steps < exact._grid.steps / 2, "the point: far fewer voxels walked"
    # free space: the skipped lateral voxels leave a few % of the known (free) voxels unknown
    known_fast = np.count_nonzero(~np.isnan(fast._grid.log_odds))
    known_exact = np.count_nonzero(~np.isnan(exact._grid.log_odds))
    assert 0.95 < known_fast / known_exact < 1.01, known_fast / known_exact


def test_a_longer_stop_is_at_least_as_close_to_exact(built):
    exact = _set(built(0.05).occupied_index())
    agreement = []
    for stop_m in (0.05, 0.3, 1e6):
        fast = _set(built(0.05, exact_free_space=False, shared_ray_stop_m=stop_m).occupied_index())
        agreement.append(len(fast & exact) / len(fast | exact))
    assert agreement[0] <= agreement[1] + 1e-3 and agreement[1] <= agreement[2] + 1e-3, agreement
    assert agreement[2] > 0.995, "without stopping only the reverse traversal's corner ties differ"


def test_shared_origin_casting_keeps_octomaps_rules():
    fused = new_map(RES, exact_free_space=False)
    origin = np.array([0.05, 0.05, 0.05])
    fused.insert_cloud(np.array([[20.05, 0.05, 0.05], [2.05, 0.05, 0.05], [2.05, 0.15, 0.05]]), origin, 6.0)
    assert _set(fused.occupied_index()) == _set(np.array([[20, 0, 0], [20, 1, 0]])), "hits within range only"
    assert fused.is_free(np.array([[1.0, 0.05, 0.05], [5.8, 0.05, 0.05], [0.05, 0.05, 0.05]])).all()
    assert not fused.is_free(np.array([[7.0, 0.05, 0.05]])).any()
    # a ray through another point's voxel of the same cloud does not clear it (occupied wins)
    fused = new_map(RES, exact_free_space=False)
    fused.insert_cloud(np.array([[1.05, 0.05, 0.05], [3.05, 0.05, 0.05]]), origin, 6.0)
    assert len(fused.occupied_index()) == 2


def test_exact_mode_equals_octomap_on_the_synthetic_hall(clouds, built):
    fused = built(RES)
    plain = plain_tree(RES)
    for k in range(5):
        for robot, frames, max_range in clouds:
            if k < len(frames):
                plain.insertPointCloud(
                    np.asarray(frames[k][0], dtype=np.float64),
                    np.asarray(frames[k][1], dtype=np.float64),
                    maxrange=max_range,
                )
    ours, theirs = _finest_voxels(fused.tree, RES), _finest_voxels(plain, RES)
    a = dict(zip(pack_index(ours[0]).tolist(), ours[1].tolist()))
    b = dict(zip(pack_index(theirs[0]).tolist(), theirs[1].tolist()))
    assert a.keys() == b.keys()
    assert max(abs(a[k] - b[k]) for k in b) < 1e-6


@pytest.mark.parametrize("exact", [True, False])
def test_binary_stream_from_the_grid_is_octomaps_own(built, exact):
    fused = built(0.05, exact_free_space=exact)
    copy = octree_from_bytes(fused.to_bytes(binary=False))
    assert fused.to_bytes(binary=True) == copy.writeBinary()
    assert fused.binary_tree_nodes() == copy.size()


def test_empty_map_writes_octomaps_empty_tree():
    fused = new_map(RES)
    assert fused.to_bytes(binary=True) == octomap.OcTree(RES).writeBinary()
    assert fused.binary_tree_nodes() == 0


def test_the_tree_is_rebuilt_only_when_the_map_changed():
    fused = new_map(RES, exact_free_space=False)
    fused.insert_cloud(np.array([[1.05, 0.05, 0.05]]), [0.05, 0.05, 0.05], 6.0)
    first = fused.tree
    assert fused.tree is first and first.size() > 0
    fused.insert_cloud(np.array([[1.05, 1.05, 0.05]]), [0.05, 0.05, 0.05], 6.0)
    assert fused.tree is not first
    assert fused.memory_bytes() > fused.stats()["grid_bytes"]


def test_stop_length_must_be_positive():
    with pytest.raises(ValueError, match="shared_ray_stop_m"):
        new_map(RES, shared_ray_stop_m=0.0)
