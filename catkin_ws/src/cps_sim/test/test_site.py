"""The hall file, its variants for change detection, and the ground-truth voxels."""

import numpy as np
import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import load_fleet
from cps_fleet.site import check_waypoint, load_site
from cps_sim.ground_truth import occupied_voxels

TYPES = load_fleet().robot_types


def test_hall_has_three_fenced_areas_and_named_equipment():
    site = load_site(load_fleet().site_path)
    assert len(site.areas) == 3
    names = [e.name for e in site.equipment]
    assert len(names) == len(set(names))
    for item in site.equipment:
        x0, y0, x1, y1 = item.footprint
        assert -10 <= x0 < x1 <= 10 and -7.5 <= y0 < y1 <= 7.5
        assert any(a.x_min_m <= x0 and x1 <= a.x_max_m and a.y_min_m <= y0 and y1 <= a.y_max_m for a in site.areas), (
            item.name
        )


def test_without_and_moved_change_one_item():
    site = load_site(load_fleet().site_path)
    assert "crate_2" not in [e.name for e in site.without("crate_2").equipment]
    moved = site.moved("crate_2", 1.0, -0.5)
    assert moved.item("crate_2").x == pytest.approx(site.item("crate_2").x + 1.0)
    assert moved.item("tank_1") == site.item("tank_1")
    with pytest.raises(KeyError):
        site.without("no_such_item")


def test_ground_truth_is_on_octomap_grid_and_sees_the_change():
    site = load_site(load_fleet().site_path)
    res = 0.1
    full = occupied_voxels(site, res)
    assert full.dtype == np.float64 and full.shape[1] == 3
    np.testing.assert_allclose(full / res - 0.5, np.round(full / res - 0.5), atol=1e-6)
    assert np.any(np.isclose(full[:, 2], -0.05))  # the floor layer
    crate = site.item("crate_2")
    near_crate_top = np.all(np.abs(full - [crate.x, crate.y, 0.95]) < [0.5, 0.5, 0.01], axis=1)
    assert near_crate_top.sum() == 100  # 1 m x 1 m top at 0.1 m
    without = occupied_voxels(site.without("crate_2"), res)
    assert len(without) < len(full)


def test_bad_hall_file_names_file_and_line(tmp_path):
    text = open(load_site(load_fleet().site_path).path).read().replace("type: drum", "type: barrel", 1)
    bad = tmp_path / "hall.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_site(bad)
    line = next(i for i, text_line in enumerate(text.splitlines(), 1) if "barrel" in text_line)
    assert f"hall.yaml:{line}:" in str(err.value) and "barrel" in str(err.value) and "known:" in str(err.value)


def test_waypoints_outside_the_hall_or_in_equipment_are_rejected():
    site = load_site(load_fleet().site_path)
    assert check_waypoint(site, 0.0, 0.0, 0.0, TYPES["wheeled_depth"]) is None
    assert "outside the hall" in check_waypoint(site, 12.0, 0.0, 0.0, TYPES["wheeled_depth"])
    tank = site.item("tank_1")
    assert "tank_1" in check_waypoint(site, tank.x, tank.y, 0.0, TYPES["wheeled_lidar"])
    assert check_waypoint(site, tank.x, tank.y, 3.0, TYPES["aerial_depth"]) is None
    assert "tank_1" in check_waypoint(site, tank.x, tank.y, 2.0, TYPES["aerial_depth"])


def test_export_ground_truth_command_writes_npz(tmp_path):
    import os
    import subprocess
    import sys

    node = os.path.join(os.path.dirname(__file__), "..", "nodes", "export_ground_truth")
    out = tmp_path / "gt.npz"
    done = subprocess.run(
        [sys.executable, node, str(out), "--resolution", "0.2", "--without", "crate_2"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    data = np.load(out)
    assert float(data["resolution_m"]) == 0.2 and data["occupied_centers_m"].shape[1] == 3
    bad = subprocess.run(
        [sys.executable, node, str(out), "--without", "crate_99"], capture_output=True, text=True, timeout=60
    )
    assert bad.returncode == 2 and "crate_99" in bad.stderr
