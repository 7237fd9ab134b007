"""FusedLogOddsMap: fusion of several robots' clouds, batching, persistence readable by OctoMap's own
tools, and every bad input (non-finite points, corrupt or wrong-type files) leaving the map intact."""

import os
import shutil
import subprocess

import numpy as np
import octomap
import pytest
import synthetic_scene as sc
from fleet_model import new_map, plain_tree

from cps_mapping.fused_map import (
    MapFileError,
    _finest_voxels,
    message_fields,
    octree_from_bytes,
    octree_from_message,
    pack_index,
    read_octree_file,
    voxel_index,
)

RES = 0.1


@pytest.fixture(scope="module")
def scene():
    return sc.hall_scene()


@pytest.fixture(scope="module")
def two_robot_clouds(scene):
    """A depth robot looking at crate_b and a lidar robot next to crate_a, a few frames each."""
    depth = sc.robot_clouds(scene, "depth", sc.trajectory([-1.0, 2.0, 0.5], [-0.8, 2.0, 0.5], 2), RES)
    lidar = sc.robot_clouds(scene, "lidar", sc.trajectory([-5.0, -1.5, 0.6], [-4.8, -1.5, 0.6], 2), 0.01)
    return depth, lidar


def _set(index):
    return set(pack_index(index).tolist())


def test_two_robots_land_in_one_map_at_the_right_places(scene, two_robot_clouds):
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, max_range_m=6.0, robot="jackal")
    fused.insert_batch(lidar, max_range_m=12.0, robot="scout")
    occupied = _set(fused.occupied_index())
    truth = _set(voxel_index(scene.occupied_voxels(RES), RES))
    assert len(occupied & truth) / len(occupied) > 0.98, "occupied voxels must lie on the scene's surfaces"
    for crate in ("crate_a", "crate_b"):
        box = next(b for b in scene.boxes if b.name == crate)
        crate_truth = _set(voxel_index(sc.BoxScene((box,)).occupied_voxels(RES), RES))
        assert len(crate_truth & occupied) > 30, f"{crate} is missing from the fused map"
    contributions = fused.contributions()
    assert set(contributions) == {"jackal", "scout"}
    assert sum(contributions.values()) == len(occupied)


def test_each_robot_alone_sees_only_its_part(scene, two_robot_clouds):
    depth, _ = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, max_range_m=6.0, robot="jackal")
    crate_b = next(b for b in scene.boxes if b.name == "crate_b")
    centers = fused.occupied_centers()
    near_b = np.all((centers >= np.asarray(crate_b.min_m) - 0.1) & (centers <= np.asarray(crate_b.max_m) + 0.1), axis=1)
    assert near_b.sum() > 30
    assert centers[:, 0].min() > -1.0, "a camera looking along +x from x=-1 cannot see behind itself"


def test_batch_holds_exactly_the_voxels_sequential_insertion_finds(scene):
    clouds = sc.robot_clouds(scene, "depth", sc.trajectory([-2.0, 0.0, 0.5], [-1.6, 0.0, 0.5], 4), RES)
    plain = plain_tree(RES)
    for points, origin in clouds:
        plain.insertPointCloud(points, origin, maxrange=6.0)
    plain_occ = {
        tuple(np.floor(np.array([it.getX(), it.getY(), it.getZ()]) / RES).astype(int))
        for it in plain.begin_leafs()
        if it.getValue() > 0
    }
    fused = new_map(RES)
    result = fused.insert_batch(clouds, max_range_m=6.0, robot="jackal")
    assert result.groups == 4 and result.clouds == 4, "every cloud is cast from its own origin"
    assert {tuple(i) for i in fused.occupied_index().tolist()} == plain_occ


def test_far_origins_are_not_merged(scene):
    clouds = sc.robot_clouds(scene, "depth", sc.trajectory([-2.0, 0.0, 0.5], [0.0, 0.0, 0.5], 3), RES)
    result = new_map(RES).insert_batch(clouds, 6.0, "jackal")
    assert result.groups == 3


def test_non_finite_and_empty_clouds(scene):
    fused = new_map(RES)
    points = np.array([[1.0, 0.0, 0.5], [np.nan, 0.0, 0.0], [np.inf, 1.0, 1.0]])
    result = fused.insert_cloud(points, [0.0, 0.0, 0.5], max_range_m=6.0, robot="jackal")
    assert result.points_rejected == 2 and result.points_inserted == 1
    assert len(fused.occupied_index()) == 1
    version = fused.version
    empty = fused.insert_cloud(np.zeros((0, 3)), [0.0, 0.0, 0.5], 6.0, "jackal")
    assert empty.points_inserted == 0 and fused.version == version
    with pytest.raises(ValueError, match="origin"):
        fused.insert_cloud(points, [np.nan, 0.0, 0.0], 6.0, "jackal")
    assert len(fused.occupied_index()) == 1


def test_max_range_limits_occupied_voxels():
    fused = new_map(RES)
    fused.insert_cloud(np.array([[3.0, 0.0, 0.0], [30.0, 0.0, 0.0]]), [0.0, 0.0, 0.0], max_range_m=6.0)
    occupied = fused.occupied_centers()
    assert len(occupied) == 1 and occupied[0][0] == pytest.approx(3.05)


@pytest.mark.parametrize("ext", [".bt", ".ot"])
def test_save_load_round_trip(tmp_path, two_robot_clouds, ext):
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    path = fused.save(str(tmp_path / f"sub/map{ext}"))
    assert os.path.exists(path) and not [f for f in os.listdir(tmp_path / "sub") if f.startswith(".tmp")]
    restored = new_map(RES)
    restored.load(path)
    assert _set(restored.occupied_index()) == _set(fused.occupied_index())


def test_saved_bt_opens_with_octomap_tools_and_equals_live_map(tmp_path, two_robot_clouds):
    if not shutil.which("convert_octree"):
        pytest.fail("octomap-tools (convert_octree) is not installed; ci/apt-packages.txt lists it")
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    fused.insert_batch(lidar, 12.0, "scout")
    bt = fused.save(str(tmp_path / "live.bt"))
    converted = tmp_path / "converted.ot"
    run = subprocess.run(["convert_octree", bt, str(converted)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and "OcTree" in run.stdout, run.stdout + run.stderr
    assert read_octree_file(str(converted), expected_resolution_m=RES).size() == _max_likelihood_copy(fused).size()
    live = {tuple(i) for i in fused.occupied_index().tolist()}
    reread = new_map(RES)
    reread.load(str(converted))
    assert {tuple(i) for i in reread.occupied_index().tolist()} == live
    ot = fused.save(str(tmp_path / "live.ot"))
    compare = subprocess.run(["compare_octrees", ot, ot], capture_output=True, text=True, timeout=60)
    assert compare.returncode == 0 and "KLD: 0" in compare.stdout, compare.stdout


def _bad_files(tmp_path):
    good = new_map(RES)
    good.insert_cloud(np.array([[1.0, 1.0, 1.0]]), [0.0, 0.0, 0.0])
    good.save(str(tmp_path / "good.bt"))
    data = (tmp_path / "good.bt").read_bytes()
    (tmp_path / "garbage.bt").write_bytes(b"\x00\x01garbage" * 50)
    (tmp_path / "truncated.bt").write_bytes(data[: len(data) - 20])
    (tmp_path / "text_as_binary.bt").write_bytes(data.replace(b"binary file", b"file", 1))
    color = octomap.ColorOcTree(RES)
    color.updateNode(np.array([0.05, 0.05, 0.05]), True)
    color.write(str(tmp_path / "color.ot").encode())
    coarse = new_map(0.2)
    coarse.insert_cloud(np.array([[1.0, 1.0, 1.0]]), [0.0, 0.0, 0.0])
    coarse.save(str(tmp_path / "coarse.bt"))
    (tmp_path / "map.png").write_bytes(data)
    return {
        "garbage.bt": "not an OctoMap file",
        "truncated.bt": "",
        "text_as_binary.bt": "extension",
        "color.ot": "ColorOcTree",
        "coarse.bt": "resolution",
        "map.png": "unknown map format",
        "missing.bt": "cannot read",
    }


def test_bad_map_files_leave_the_running_map_untouched(tmp_path, two_robot_clouds):
    depth, _ = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    before = _set(fused.occupied_index())
    for name, reason in _bad_files(tmp_path).items():
        with pytest.raises(MapFileError, match=reason) as info:
            fused.load(str(tmp_path / name))
        assert name in str(info.value)
        assert _set(fused.occupied_index()) == before, f"loading {name} changed the map"


def test_octomap_message_round_trip(two_robot_clouds):
    depth, _ = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    binary, tree_id, res, body = message_fields(fused)
    assert binary and tree_id == "OcTree" and res == pytest.approx(RES)
    assert not body.startswith(b"#"), "the message body carries no file header, as octomap_msgs"
    tree = octree_from_message(binary, tree_id, res, body)
    assert tree.size() == _max_likelihood_copy(fused).size()


def _max_likelihood_copy(fused):
    """What OctoMap's writeBinary makes of the live tree (max likelihood, pruned), on a copy."""
    copy = octree_from_bytes(fused.to_bytes(binary=False))
    copy.writeBinary()
    return copy


def test_writing_binary_keeps_the_log_odds_and_equals_octomaps_own(tmp_path, two_robot_clouds):
    """OctoMap's writeBinary turns the tree it writes into max likelihood; publishing or saving
    a .bt must neither do that to the live map nor write anything else than it would."""
    depth, lidar = two_robot_clouds
    fused, untouched = new_map(RES), new_map(RES)
    steps = [
        lambda m: m.insert_batch(depth[:1], 6.0, "jackal"),
        lambda m: m.insert_batch(lidar, 12.0, "scout"),
        lambda m: m.clear_bbx([-1.0, -1.0, 0.0], [1.0, 1.0, 1.0]),
        lambda m: m.insert_batch(depth[1:], 6.0, "jackal"),
    ]
    for step in steps:
        step(fused)
        step(untouched)
        assert fused.to_bytes(binary=True) == _max_likelihood_copy(fused).writeBinary()
        fused.save(str(tmp_path / "live.bt"))
        ours, expected = _finest_voxels(fused.tree, RES), _finest_voxels(untouched.tree, RES)
        assert np.array_equal(ours[0], expected[0]) and np.array_equal(ours[1], expected[1])
    values = ours[1]
    assert len(np.unique(values)) > 2, "the live map holds log-odds, not only the two clamping bounds"


def test_clear_bbx_frees_only_inside(scene, two_robot_clouds):
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    fused.insert_batch(lidar, 12.0, "scout")
    crate_b = next(b for b in scene.boxes if b.name == "crate_b")
    lo, hi = np.asarray(crate_b.min_m) - 0.2, np.asarray(crate_b.max_m) + 0.2
    before = fused.occupied_centers()
    fused.clear_bbx(lo, hi)
    after = fused.occupied_centers()
    inside = np.all((after >= lo) & (after <= hi), axis=1)
    assert not inside.any()
    outside_before = before[~np.all((before >= lo) & (before <= hi), axis=1)]
    assert len(after) == len(outside_before)
    with pytest.raises(ValueError):
        fused.clear_bbx(hi, lo)


def test_projected_map_marks_crates_and_free_floor(scene, two_robot_clouds):
    _, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(lidar, 12.0, "scout")
    grid, origin = fused.projected_grid(z_min_m=0.2, z_max_m=2.0)
    crate_a = next(b for b in scene.boxes if b.name == "crate_a")
    cx, cy = (np.asarray(crate_a.min_m[:2]) + crate_a.max_m[:2]) / 2
    col, row = int((crate_a.min_m[0] + 0.05 - origin[0]) / RES), int((cy - origin[1]) / RES)
    assert grid[row, col] == 100
    robot_col, robot_row = int((-4.9 - origin[0]) / RES), int((-1.5 - origin[1]) / RES)
    assert grid[robot_row, robot_col] in (0, -1)
    assert (grid == 0).sum() > (grid == 100).sum()


def test_projected_map_equals_the_projection_of_every_known_voxel(two_robot_clouds):
    """The column-wise projection of the dense grid equals octomap_server's leaf by leaf one."""
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    fused.insert_batch(lidar, 12.0, "scout")
    for z_min, z_max in ((0.2, 2.0), (-np.inf, np.inf), (0.55, 0.6)):
        leaves = fused.leaves()
        z = leaves.centers_m[:, 2]
        band = (z + RES / 2 >= z_min) & (z - RES / 2 <= z_max)
        xy = np.floor(leaves.centers_m[band, :2] / RES).astype(int)
        lo = xy.min(axis=0)
        expected = np.full(tuple((xy.max(axis=0) - lo + 1)[::-1]), -1, dtype=np.int8)
        expected[xy[:, 1] - lo[1], xy[:, 0] - lo[0]] = 0
        occupied = xy[leaves.occupied[band]]
        expected[occupied[:, 1] - lo[1], occupied[:, 0] - lo[0]] = 100
        grid, origin = fused.projected_grid(z_min_m=z_min, z_max_m=z_max)
        np.testing.assert_array_equal(grid, expected)
        np.testing.assert_allclose(origin, lo * RES)
    grid, _ = fused.projected_grid(z_min_m=50.0, z_max_m=60.0)
    assert grid.shape == (1, 1) and grid[0, 0] == -1
    assert new_map(RES).projected_grid()[0].shape == (1, 1)


def test_reset_empties_the_map(two_robot_clouds):
    depth, _ = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    fused.reset()
    assert len(fused.occupied_index()) == 0 and fused.contributions() == {}


def test_is_free_agrees_with_octomap_and_asks_for_firmer_evidence_on_request(two_robot_clouds):
    fused = new_map(RES)
    origin, target, crossed = [0.05, 0.05, 0.05], [[2.05, 0.05, 0.05]], [[1.05, 0.05, 0.05]]
    for clouds in (1, 2, 3):
        fused.insert_cloud(np.array(target), origin)
        assert fused.is_free(crossed)[0], "one miss (probability 0.4) is free for OctoMap"
        assert fused.is_free(crossed, max_probability=0.25)[0] == (clouds >= 3), "p = 0.25 takes three misses"
    assert not fused.is_free(target)[0] and not fused.is_free([[9.0, 9.0, 9.0]])[0], "occupied, unknown"
    with pytest.raises(ValueError, match="max_probability"):
        fused.is_free(crossed, max_probability=1.0)
    depth, _ = two_robot_clouds
    fused.insert_batch(depth, 6.0, "jackal")
    probes = np.random.default_rng(1).uniform([-3.0, -1.0, 0.0], [4.0, 5.0, 2.0], size=(5000, 3))
    assert np.array_equal(fused.is_free(probes), fused.tree.getLabels(probes) == 0)


def test_leaves_read_from_the_grid_are_the_trees_leaves(two_robot_clouds):
    depth, lidar = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    fused.insert_batch(lidar, 12.0, "scout")
    rows = np.array([(it.getX(), it.getY(), it.getZ(), it.getSize(), it.getValue()) for it in fused.tree.begin_leafs()])
    leaves = fused.leaves()
    # pytest.approx's default tolerance (1e-6 relative), vectorized: approx compared the 280 000
    # sizes one Python call each (2-4 CPU-s)
    assert np.all(leaves.sizes_m == RES) and np.all(np.abs(rows[:, 3] - RES) <= 1e-6 * RES)
    ours = dict(zip(map(tuple, np.round(leaves.centers_m, 4).tolist()), leaves.log_odds.tolist()))
    assert ours == dict(zip(map(tuple, np.round(rows[:, :3], 4).tolist()), rows[:, 4].tolist()))


def test_a_log_odds_copy_holds_every_known_voxel_and_stays_as_it_was(two_robot_clouds):
    depth, _ = two_robot_clouds
    fused = new_map(RES)
    fused.insert_batch(depth, 6.0, "jackal")
    box = fused.log_odds_copy()
    leaves = fused.leaves()
    cells = np.ravel_multi_index((voxel_index(leaves.centers_m, RES) - box.lo).T, box.dims)
    assert np.array_equal(box.log_odds[cells], leaves.log_odds.astype(np.float32))
    assert np.count_nonzero(~np.isnan(box.log_odds)) == len(cells), "every other cell unknown"
    before = box.log_odds.copy()
    assert fused.clear_bbx([-50.0, -50.0, -50.0], [50.0, 50.0, 50.0]) == len(cells)  # in place
    assert np.array_equal(box.log_odds, before, equal_nan=True), "a copy, not a view of the live grid"


def test_a_far_origin_cannot_grow_the_grid_beyond_its_limit():
    fused = new_map(RES, max_grid_voxels=2_000_000)
    fused.insert_cloud(np.array([[3.0, 0.0, 0.5]]), [0.0, 0.0, 0.5], max_range_m=6.0)
    before, grid_bytes = _set(fused.occupied_index()), fused.stats()["grid_bytes"]
    near, far = (np.array([[1.0, 1.0, 0.5]]), [0.0, 0.0, 0.5]), (np.array([[900.0, 0.0, 0.5]]), [901.0, 0.0, 0.5])
    with pytest.raises(ValueError, match="nothing inserted"):
        fused.insert_batch([near, far], max_range_m=6.0, robot="jackal")
    assert _set(fused.occupied_index()) == before and fused.stats()["grid_bytes"] == grid_bytes
    with pytest.raises(ValueError, match="over the limit"):
        fused.insert_cloud(np.array([[150.0, 150.0, 0.5]]), [0.0, 0.0, 0.5], max_range_m=-1.0)
    fused.insert_batch([near], max_range_m=6.0, robot="jackal")
    assert len(_set(fused.occupied_index())) == len(before) + 1


@pytest.mark.parametrize("exact", [True, False])
def test_first_seen_stamps_are_the_first_cloud_that_crossed_or_hit_each_voxel(two_robot_clouds, exact):
    """A monitoring mission times a change from the cloud that first saw its place (issue 39): each
    voxel keeps the stamp of the first cloud whose ray crossed or ended in it, through the grid's
    growth, and the map is the same map with or without the stamps."""
    depth, lidar = two_robot_clouds
    plain, stamped = new_map(RES, exact_free_space=exact), new_map(RES, exact_free_space=exact, first_seen_stamps=True)
    stamps = [1000.0 + 0.5 * k for k in range(len(depth))]
    for fused in (plain, stamped):
        fused.insert_batch(depth, 6.0, "jackal", stamps_s=stamps if fused is stamped else None)
    later = 2000.0
    for fused in (plain, stamped):  # the lidar far away: the grid grows, the stamps move with it
        fused.insert_batch(lidar, 12.0, "scout", stamps_s=[later] * len(lidar) if fused is stamped else None)
    assert np.array_equal(plain.log_odds_copy().log_odds, stamped.log_odds_copy().log_odds, equal_nan=True)
    box = stamped.log_odds_copy()
    known = ~np.isnan(box.log_odds)
    assert np.array_equal(known, ~np.isnan(box.first_seen_s)), "every known voxel has a first stamp"
    first_only = new_map(RES, exact_free_space=exact)
    first_only.insert_batch(depth[:1], 6.0, "jackal")
    seen_first = first_only.leaves().centers_m
    assert np.all(stamped.first_seen_s(seen_first) == stamps[0]), "what the first cloud saw keeps its stamp"
    depth_only = new_map(RES, exact_free_space=exact)
    depth_only.insert_batch(depth, 6.0, "jackal")
    by_depth = set(pack_index(voxel_index(depth_only.leaves().centers_m, RES)).tolist())
    centres = stamped.leaves().centers_m
    by_lidar_only = centres[[p not in by_depth for p in pack_index(voxel_index(centres, RES)).tolist()]]
    assert len(by_lidar_only) and np.all(stamped.first_seen_s(by_lidar_only) == later)
    assert (
        np.isnan(stamped.first_seen_s([[500.0, 500.0, 0.5]])).all() and np.isnan(plain.first_seen_s(seen_first)).all()
    )
    with pytest.raises(ValueError, match="stamps for"):
        stamped.insert_batch(depth, 6.0, "jackal", stamps_s=[1.0])
