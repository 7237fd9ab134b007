"""The changes file of a monitoring mission: read against the site, bad entries named by file:line,
and the simulator's list of what a detector should find."""

import os

import pytest

from cps_fleet.config import ConfigError
from cps_fleet.fleet import load_fleet
from cps_fleet.site import load_site
from cps_sim.site_changes import expected_changes, load_site_changes

EXAMPLE = os.path.join(os.path.dirname(__file__), "..", "..", "cps_bringup", "config", "site_changes.yaml")


@pytest.fixture(scope="module")
def site():
    return load_site(load_fleet().site_path)


def _write(tmp_path, text):
    path = tmp_path / "changes.yaml"
    path.write_text(text)
    return str(path)


def test_example_removes_one_crate_and_moves_another_by_one_metre(site):
    changes = load_site_changes(EXAMPLE, site)
    assert changes.removed == ("crate_2",)
    (move,) = changes.moved
    assert move.name == "crate_4" and abs(move.dx_m**2 + move.dy_m**2 - 1.0) < 1e-9
    after = changes.apply(site)
    assert "crate_2" not in (e.name for e in after.equipment)
    assert after.item("crate_4").y == pytest.approx(site.item("crate_4").y + move.dy_m)

    expected = {(e.name, e.kind): e for e in expected_changes(site, changes)}
    assert set(expected) == {("crate_2", "disappeared"), ("crate_4", "moved")}  # a move is one change
    assert expected[("crate_2", "disappeared")].centroid_m == pytest.approx((3.2, -1.0, 0.5))
    moved = expected[("crate_4", "moved")]
    assert moved.centroid_m[1] - moved.from_centroid_m[1] == pytest.approx(move.dy_m)
    assert moved.displacement_m == pytest.approx((0.0, move.dy_m, 0.0)) and moved.from_size_m == moved.size_m


def test_added_box_and_cylinder_appear(site, tmp_path):
    path = _write(
        tmp_path,
        "added:\n"
        "  - {name: new_box, shape: box, x: 0.0, y: 0.0, size_x_m: 0.6, size_y_m: 0.4, size_z_m: 0.8}\n"
        "  - {name: new_drum, shape: cylinder, x: 1.0, y: 2.0, radius_m: 0.3, height_m: 0.9}\n",
    )
    changes = load_site_changes(path, site)
    assert len(changes.apply(site).equipment) == len(site.equipment) + 2
    box, drum = expected_changes(site, changes)
    assert box.kind == drum.kind == "appeared"
    assert box.size_m == pytest.approx((0.6, 0.4, 0.8))
    assert drum.centroid_m == pytest.approx((1.0, 2.0, 0.45))


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("removed: [crate_2, crate_99]\n", 1, "no equipment named 'crate_99'"),
        ("removed: []\nmoved:\n  - {name: crate_99, dx_m: 1.0}\n", 3, "no equipment named 'crate_99'"),
        (
            "moved:\n  - {name: crate_2, dx_m: 0.5}\n  - {name: crate_4, dx_m: 0.0, dy_m: -3.0}\n",
            3,
            "would leave the hall",
        ),
        (
            "added:\n  - {name: tank_1, shape: box, x: 0, y: 0, size_x_m: 1, size_y_m: 1, size_z_m: 1}\n",
            2,
            "already used",
        ),
        ("added:\n  - {name: cone, shape: cone, x: 0, y: 0}\n", 2, "unknown shape"),
        (
            "added:\n  - {name: big, shape: cylinder, x: 9.8, y: 0, radius_m: 0.5, height_m: 1}\n",
            2,
            "would leave the hall",
        ),
        ("remove: [crate_2]\n", 1, "unknown key"),
    ],
)
def test_bad_changes_are_named_with_file_and_line(site, tmp_path, text, line, words):
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_site_changes(path, site)
    assert f"{path}:{line}:" in str(info.value) and words in str(info.value)
