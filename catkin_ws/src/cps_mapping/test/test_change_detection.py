"""Change detection between two missions in the simulated hall: a moved crate is found (where it
went and where it was) and nothing else; a removed one is found as disappeared."""

import numpy as np
import pytest
from fleet_model import new_map

from cps_fleet.fleet import load_fleet
from cps_mapping.change_detection import detect_changes, detect_map_changes, write_report

RES = 0.1
# Views of the storage area (crate_2 stands at x=3.2, y=-1.0, 1 m cube) from outside its fence.
POSES = {
    "jackal": [(0.0, -0.25, 0.0, -25.0), (0.0, -0.25, 0.0, 0.0), (0.0, -0.25, 0.0, 25.0), (0.5, -2.0, 0.0, 10.0)],
    "scout": [(0.0, -1.0, 0.0, 0.0)],
}


def _mission(site):
    from sim_views import capture_views

    views = capture_views(POSES, site=site, robots=("jackal", "scout"))
    fused = new_map(RES)
    fused.insert_batch(views["jackal"], 6.0, "jackal")
    fused.insert_batch(views["scout"], 12.0, "scout")
    return fused


@pytest.fixture(scope="module")
def site():
    from cps_fleet.site import load_site

    return load_site(load_fleet().site_path)


@pytest.fixture(scope="module")
def baseline(site):
    return _mission(site)


def test_same_site_twice_has_no_changes(site, baseline):
    assert detect_map_changes(baseline, _mission(site)) == []


def test_moved_crate_is_found_and_nothing_else(site, baseline, tmp_path):
    crate = site.item("crate_2")
    current = _mission(site.moved("crate_2", 0.0, 1.5))
    changes = detect_map_changes(baseline, current)
    kinds = sorted(c.kind for c in changes)
    assert kinds == ["appeared", "disappeared"], [(c.kind, c.centroid_m, c.voxels) for c in changes]
    appeared = next(c for c in changes if c.kind == "appeared")
    gone = next(c for c in changes if c.kind == "disappeared")
    assert abs(appeared.centroid_m[1] - (crate.y + 1.5)) < 0.6 and abs(appeared.centroid_m[0] - crate.x) < 0.8
    assert abs(gone.centroid_m[1] - crate.y) < 0.6 and abs(gone.centroid_m[0] - crate.x) < 0.8
    assert all(0.05 < c.volume_m3 < 1.5 and max(c.size_m) <= 1.3 for c in changes)
    report = write_report(changes, tmp_path / "changes.md")
    text = open(report).read()
    assert "appeared" in text and "disappeared" in text and (tmp_path / "changes.json").exists()


def test_removed_crate_is_disappeared(site, baseline):
    changes = detect_map_changes(baseline, _mission(site.without("crate_2")))
    assert [c.kind for c in changes] == ["disappeared"], [(c.kind, c.centroid_m, c.voxels) for c in changes]


def test_tolerance_and_cluster_size_filter_jitter():
    rng = np.random.default_rng(0)
    plane = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0], indexing="ij"), axis=-1).reshape(-1, 3)
    base = (plane + 0.5) * RES
    jittered = base + rng.integers(-1, 2, size=base.shape) * np.array([0, 0, RES])
    assert detect_changes(base, jittered, RES) == []
    box = (
        np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(1, 6), indexing="ij"), axis=-1).reshape(-1, 3)
        + [10, 10, 0]
        + 0.5
    ) * RES
    changes = detect_changes(base, np.vstack([base, box]), RES)
    assert len(changes) == 1 and changes[0].kind == "appeared"
    assert changes[0].voxels < len(box), "the box's bottom layer touches the floor and falls within tolerance"


@pytest.mark.parametrize("dx_m, dy_m", [(0.0, 0.5), (0.3, -0.6), (0.0, 1.5)])
def test_a_moved_crate_is_one_moved_change_with_its_displacement(site, baseline, dx_m, dy_m):
    """A move shorter than the crate (0.5 m of 1 m: only slivers change) or longer is one change,
    displaced by the move within a voxel (issue 39: moves were two changes 0.46 m off)."""
    from cps_mapping.change_detection import ChangeRules

    crate = site.item("crate_2")
    changes = detect_map_changes(
        baseline, _mission(site.moved("crate_2", dx_m, dy_m)), rules=ChangeRules(move_radius_m=5.0)
    )
    assert [c.kind for c in changes] == ["moved"], [(c.kind, c.centroid_m, c.voxels) for c in changes]
    (move,) = changes
    assert move.displacement_m[0] == pytest.approx(dx_m, abs=0.1) and move.displacement_m[1] == pytest.approx(
        dy_m, abs=0.1
    )
    assert move.from_m[0] == pytest.approx(crate.x, abs=0.2) and move.from_m[1] == pytest.approx(crate.y, abs=0.2)
    assert move.place_m[0] == pytest.approx(crate.x + dx_m, abs=0.2) and move.place_m[1] == pytest.approx(
        crate.y + dy_m, abs=0.2
    )
