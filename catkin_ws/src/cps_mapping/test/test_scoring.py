"""The scorer against cps_sim's ground truth: F1 = 1 for the truth itself, lower for a damaged
map; a map built from simulated views scores sensibly, with each robot's contribution."""
import numpy as np
import pytest

from cps_mapping.scoring import load_ground_truth, observable_surface, score_fused_map, score_map
from fleet_model import new_map
from cps_fleet.fleet import load_fleet

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
    assert score.truth_voxels == len(centers) and score.observable_voxels < score.truth_voxels


def test_damaged_map_scores_lower(truth):
    centers, _ = load_ground_truth(truth)
    rng = np.random.default_rng(1)
    kept = centers[rng.random(len(centers)) > 0.3]
    noise = rng.uniform([-9, -7, 0.2], [9, 7, 1.8], size=(len(centers) // 10, 3))
    score = score_map(np.vstack([kept, noise]), truth, tolerance_voxels=0)
    assert score.recall == pytest.approx(0.7, abs=0.02)
    assert score_map(np.vstack([kept, noise]), truth).f1 < 0.95
    assert score.precision < 0.95 and score.f1 < 0.85
    assert score_map(kept, truth).precision == 1.0
    shifted = score_map(centers + [0.0, 0.0, RES], truth)
    assert shifted.f1 == 1.0 and score_map(centers + [0.0, 0.0, RES], truth, tolerance_voxels=0).f1 < 0.6


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

    views = capture_views({"jackal": [(-6.6, 1.8, 0.0, 35.0), (-6.0, 0.0, 0.0, 0.0)],
                           "scout": [(-6.5, -2.6, 0.0, 0.0)]}, robots=("jackal", "scout"))
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
