"""The scorer against cps_sim's ground truth: F1 = 1 for the truth itself, lower for a damaged
map; a map built from simulated views scores sensibly, with each robot's contribution."""

import numpy as np
import pytest
from fleet_model import new_map

from cps_fleet.fleet import load_fleet
from cps_mapping.scoring import (
    load_ground_truth,
    observable_surface,
    read_scores,
    score_fused_map,
    score_map,
    tolerance_label,
)

RES = 0.1


@pytest.fixture(scope="module")
def site():
    from cps_fleet.site import load_site

    return load_site(load_fleet().site_path)


@pytest.fixture(scope="module")
def truth(site, tmp_path_factory):
    from cps_sim.ground_truth import save_ground_truth

    path = tmp_path_factory.mktemp("gt") / "hall.npz"
    save_ground_truth(str(path), site, RES)
    return str(path)


def test_truth_against_itself_is_perfect(truth):
    centers, res = load_ground_truth(truth)
    score = score_map(centers, truth)
    assert (score.precision, score.recall, score.f1, score.coverage) == (1.0, 1.0, 1.0, 1.0)
    assert (score.exact.precision, score.exact.recall, score.exact.f1) == (1.0, 1.0, 1.0)
    assert score.truth_voxels == len(centers) and score.observable_voxels < score.truth_voxels


def test_damaged_map_scores_lower(truth):
    centers, _ = load_ground_truth(truth)
    rng = np.random.default_rng(1)
    kept = centers[rng.random(len(centers)) > 0.3]
    noise = rng.uniform([-9, -7, 0.2], [9, 7, 1.8], size=(len(centers) // 10, 3))
    score = score_map(np.vstack([kept, noise]), truth)
    assert score.exact.recall == pytest.approx(0.7, abs=0.02)
    assert score.tolerant.f1 < 0.95
    assert score.exact.precision < 0.95 and score.exact.f1 < 0.85
    assert score_map(kept, truth).exact.precision == 1.0
    shifted = score_map(centers + [0.0, 0.0, RES], truth)
    assert shifted.tolerant.f1 == 1.0 and shifted.exact.f1 < 0.6


def test_observable_surface_excludes_hidden_voxels():
    solid = np.stack(np.meshgrid(*(np.arange(3),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    observable = observable_surface(solid, RES)
    assert len(observable) == 26, "the centre of a 3x3x3 block is hidden"
    only_top_seen = observable_surface(solid, RES, is_free=lambda p: p[:, 2] > 0.25)
    assert len(only_top_seen) == 9


def test_resolution_mismatch_is_refused(truth):
    centers, _ = load_ground_truth(truth)
    with pytest.raises(ValueError, match="resolution"):
        score_map(centers, truth, resolution_m=0.05)


def test_map_of_simulated_views_and_contributions(truth):
    from sim_views import capture_views

    views = capture_views(
        {"jackal": [(-6.6, 1.8, 0.0, 35.0), (-6.0, 0.0, 0.0, 0.0)], "scout": [(-6.5, -2.6, 0.0, 0.0)]},
        robots=("jackal", "scout"),
    )
    fused = new_map(RES)
    fused.insert_batch(views["jackal"], 6.0, "jackal")
    fused.insert_batch(views["scout"], 12.0, "scout")
    score = score_fused_map(fused, truth)
    assert score.precision > 0.85, score
    assert 0.0 < score.recall < score.coverage <= 1.0
    assert set(score.robots) == {"jackal", "scout"}
    assert sum(r.occupied_voxels for r in score.robots.values()) == score.map_voxels
    assert all(r.precision > 0.8 and r.coverage > 0.0 for r in score.robots.values())


def test_an_empty_map_scores_zero_instead_of_failing(truth):
    """A mission whose map server inserted nothing (no transform ever arrived) still gets a score."""
    empty = new_map(RES)
    assert not empty.is_free(np.array([[1.0, 2.0, 0.5]])).any()
    score = score_fused_map(empty, truth)
    assert score.f1 == 0.0 and score.map_voxels == 0


def _block(lo, hi):
    """Voxel centres (RES grid) of the box of indices lo..hi-1 in each axis."""
    index = np.stack(np.meshgrid(*(np.arange(lo, hi),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return (index + 0.5) * RES


def test_exact_and_tolerant_scores_on_a_small_grid():
    """A 4x4x4 truth; the map has half of it, one voxel shifted by one and one voxel far off."""
    truth = {"resolution_m": RES, "occupied_centers_m": _block(0, 4)}
    half = _block(0, 4)[:32]
    shifted_one = _block(0, 4)[-1:] + [RES, 0.0, 0.0]
    far = np.array([[2.05, 2.05, 2.05]])
    score = score_map(np.vstack([half, shifted_one, far]), truth)
    assert score.map_voxels == 34 and score.truth_voxels == 64
    assert score.exact.true_positives == 32 and score.exact.precision == pytest.approx(32 / 34)
    assert score.exact.recall == pytest.approx(32 / 64)
    assert score.tolerant.true_positives == 33 and score.tolerant.precision == pytest.approx(33 / 34)
    assert score.tolerant.recall > score.exact.recall
    assert score.exact.f1 == pytest.approx(2 * (32 / 34) * 0.5 / (32 / 34 + 0.5))


def test_a_truth_grown_by_one_voxel_is_not_exactly_precise():
    """The old score gave a map one voxel too thick in every direction precision 1.000; the exact
    figure says what it is (64 of 216 voxels true)."""
    truth = {"resolution_m": RES, "occupied_centers_m": _block(0, 4)}
    grown = score_map(_block(-1, 5), truth)
    assert grown.tolerant.precision == 1.0 and grown.tolerant.recall == 1.0
    assert grown.exact.precision == pytest.approx(64 / 216) and grown.exact.recall == 1.0
    assert grown.exact.f1 < 0.5


def test_score_keys_name_their_tolerance():
    truth = {"resolution_m": RES, "occupied_centers_m": _block(0, 3)}
    doc = score_map(_block(0, 3), truth, tolerance_voxels=2).as_dict()
    assert tolerance_label(0) == "exact" and tolerance_label(1) == "within_1_voxel"
    assert {
        "f1_exact",
        "precision_exact",
        "recall_exact",
        "f1_within_2_voxels",
        "coverage_within_2_voxels",
        "observable_from",
    } <= set(doc)
    assert not {"f1", "precision", "recall", "coverage"} & set(doc)
    assert read_scores(doc)["definition"] == "current"


def test_old_scores_json_is_read_as_within_1_voxel():
    old = {"resolution_m": 0.1, "precision": 0.95, "recall": 0.9, "f1": 0.92, "coverage": 0.98, "robots": {}}
    doc = read_scores(old)
    assert doc["f1_within_1_voxel"] == 0.92 and doc["precision_within_1_voxel"] == 0.95
    assert "f1_exact" not in doc and "f1" not in doc and doc["definition"].startswith("old")


def test_observable_surface_from_poses_does_not_depend_on_the_map():
    """Given the observable voxels (ray-cast from poses), coverage is judged against them whatever
    the map saw; the map-free-space definition shrinks with the map."""
    truth = {"resolution_m": RES, "occupied_centers_m": _block(0, 4)}
    top = _block(0, 4)[_block(0, 4)[:, 2] > 0.35]
    small_map = top[:4]
    by_poses = score_map(small_map, truth, is_free=lambda p: np.zeros(len(p), bool), observable_centers_m=top)
    assert by_poses.observable_from == "sensor poses" and by_poses.observable_voxels == 16
    assert by_poses.coverage == pytest.approx(len(near(small_map, top)) / 16)
    by_map = score_map(small_map, truth, is_free=lambda p: np.zeros(len(p), bool))
    assert by_map.observable_from == "scored map's free space" and by_map.observable_voxels == 0


def near(points, candidates):
    """The candidates within one voxel of any of `points` (the tolerant match, by brute force)."""
    return [c for c in candidates if (np.abs(points - c).max(axis=1) < 1.5 * RES).any()]
