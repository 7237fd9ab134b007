"""The evidence a change needs, piece by piece: a copy of the map answers as the map does; hits and
misses survive saving as levels; a wall seen through free space counts as a viewpoint and one seen
through an obstacle does not; a surface seen in one cloud is no change under min_hits; faces of one
item cut apart by the tolerance are one change."""

import zipfile

import numpy as np
from fleet_model import new_map

from cps_mapping.change_detection import (
    ChangeRules,
    FrozenMap,
    VoxelLevels,
    detect_changes,
    detect_map_changes,
    miss_levels,
    savez_fast,
    viewpoints_of,
    write_hit_levels,
)
from cps_mapping.fused_map import voxel_index

RES = 0.1


def _wall(x_m, y0=-1.0, y1=1.0, z1=1.0):
    ys, zs = np.meshgrid(np.arange(y0, y1, RES / 2), np.arange(0.05, z1, RES / 2))
    return np.stack([np.full(ys.size, x_m), ys.ravel(), zs.ravel()], axis=1)


def _seen(points, origin, times):
    fused = new_map(RES)
    for _ in range(times):
        fused.insert_batch([(points, np.asarray(origin, dtype=float))], 20.0, "r")
    return fused


def test_frozen_copy_answers_as_the_map_and_levels_survive_saving(tmp_path):
    fused = _seen(_wall(2.0), (0.0, 0.0, 0.5), 3)
    frozen = FrozenMap(fused)
    probe = np.random.default_rng(0).uniform([-1, -2, 0], [3, 2, 1.2], size=(5000, 3))
    for p in (0.12, 0.25, 0.5):
        assert (frozen.is_free(probe, p) == fused.is_free(probe, p)).all()
    assert (frozen.occupied_centers() == fused.occupied_centers()).all()
    index, level = frozen.hit_levels()
    assert len(index) and (level == 3).mean() > 0.9, np.bincount(level)
    path = write_hit_levels(str(tmp_path / "map.bt"), frozen)
    back = VoxelLevels.load(path)
    centres = (index + 0.5) * RES
    assert back.at_least(centres, RES, 3).mean() > 0.9 and not back.at_least(centres, RES, 4).any()
    # misses: the wall's voxels seen free k times by a later mission that finds it gone
    gone = _seen(_wall(3.0, -2.0, 2.0, 1.6), (0.0, 0.0, 0.5), 2)  # rays through x = 2 on the way to x = 3
    idx, misses = miss_levels(fused, FrozenMap(gone))
    assert (misses[np.isin(idx[:, 0], [20])] >= 2).mean() > 0.8


def test_levels_are_saved_deflated_and_load_back_exactly(tmp_path):
    rng = np.random.default_rng(1)
    arrays = {
        "index": rng.integers(0, 300, (20000, 3), dtype=np.int32),
        "level": rng.integers(1, 9, 20000, dtype=np.uint8),
    }
    path = tmp_path / "levels.npz"
    with open(path, "wb") as stream:
        savez_fast(stream, **arrays)
    with np.load(path) as back:
        assert sorted(back.files) == ["index", "level"]
        assert all(np.array_equal(back[k], v) and back[k].dtype == v.dtype for k, v in arrays.items())
    with zipfile.ZipFile(path) as archive:
        assert {i.compress_type for i in archive.infolist()} == {zipfile.ZIP_DEFLATED}
        assert sum(i.compress_size for i in archive.infolist()) < sum(i.file_size for i in archive.infolist())


def test_a_viewpoint_counts_only_through_known_free_space():
    fused = _seen(np.vstack([_wall(2.0), _wall(4.0)]), (0.0, 0.0, 0.5), 2)
    change = type("C", (), {"min_m": (4.0, -0.5, 0.0), "max_m": (4.1, 0.5, 1.0), "size_m": (0.1, 1.0, 1.0)})
    free = FrozenMap(fused).is_free
    # from beyond the wall at x = 4 (unknown space behind it) and through the wall at x = 2: none
    assert viewpoints_of(change, [[0.0, 0.0, 0.5], [6.0, 0.0, 0.5]], free, RES, 8.0) == 0
    seen = _seen(_wall(4.0), (3.0, 0.0, 0.5), 2)
    seen.insert_batch([(_wall(4.0), np.array([3.0, -0.5, 0.5]))], 20.0, "r")
    assert (
        viewpoints_of(change, [[3.0, 0.0, 0.5], [3.0, -0.5, 0.5], [9.0, 0, 0.5]], FrozenMap(seen).is_free, RES, 8.0)
        == 2
    )


def test_a_surface_seen_in_one_cloud_is_no_change_under_min_hits():
    base = _seen(_wall(3.0), (0.0, 0.0, 0.5), 4)  # the space in front of the wall seen free
    once = _seen(_wall(1.5, -0.3, 0.3, 0.8), (0.0, 0.0, 0.5), 1)  # something there, in one cloud
    twice = _seen(_wall(1.5, -0.3, 0.3, 0.8), (0.0, 0.0, 0.5), 2)
    lenient, strict = ChangeRules(min_cluster_voxels=4), ChangeRules(min_cluster_voxels=4, min_hits=2)
    assert [c.kind for c in detect_map_changes(base, FrozenMap(once), rules=lenient)] == ["appeared"]
    assert detect_map_changes(base, FrozenMap(once), rules=strict) == []
    assert [c.kind for c in detect_map_changes(base, FrozenMap(twice), rules=strict)] == ["appeared"]


def test_faces_cut_apart_by_the_tolerance_are_one_change():
    res = RES
    face_a = np.stack(np.meshgrid(np.arange(10, 11), np.arange(0, 6), np.arange(0, 6), indexing="ij"), -1).reshape(
        -1, 3
    )
    face_b = face_a + [3, 0, 0]  # 2 empty voxels between
    pts = (np.vstack([face_a, face_b]) + 0.5) * res
    apart = detect_changes(np.zeros((0, 3)), pts, res, min_cluster_voxels=4)
    merged = detect_changes(np.zeros((0, 3)), pts, res, min_cluster_voxels=4, merge_gap_voxels=1)
    assert len(apart) == 2 and len(merged) == 1 and merged[0].voxels == len(pts)
    assert voxel_index(pts, res).shape == (72, 3)
