"""The report's map scores: the robots' positions round-trip through trajectories.csv, and the
observable surface ray-cast from them is the same whichever map is scored (the committed demo's
map and an empty one), while the map-free-space definition shrinks to nothing for the empty map."""

import os

import numpy as np
import pytest

from cps_experiments.report import read_trajectories, score_saved_map, write_trajectories

DEMO_MAP = os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "docs", "results", "demo", "map.bt")
# Two positions of jackal's route in the committed demo (its start and a point of its aisle).
POSITIONS = {"jackal": ((-8.0, 6.0, 0.0), (-6.0, 6.5, 0.0))}


def test_trajectories_round_trip_and_bad_rows_are_skipped(tmp_path):
    path = str(tmp_path / "trajectories.csv")
    write_trajectories(path, {"scout": ((0.0, 1.0, 0.0), (0.5, 1.25, 0.0)), "iris": ((1.0, 1.0, 3.0),)})
    with open(path, "a") as stream:
        stream.write("scout,2,nan,1.0,0.0\n")
    back = read_trajectories(path)
    assert sorted(back) == ["iris", "scout"]
    assert back["scout"].tolist() == [[0.0, 1.0, 0.0], [0.5, 1.25, 0.0]]
    assert read_trajectories(str(tmp_path / "missing.csv")) == {}


@pytest.fixture(scope="module")
def fleet():
    from cps_fleet.fleet import load_fleet

    return load_fleet(None, profile="light")


@pytest.mark.slow
def test_the_observable_surface_from_positions_does_not_depend_on_the_map(tmp_path, fleet):
    from cps_mapping.fused_map import FusedLogOddsMap

    empty_map = str(tmp_path / "empty.bt")
    FusedLogOddsMap.from_mapping_config(fleet.mapping).save(empty_map)
    truth = str(tmp_path / "truth.npz")
    demo, _ = score_saved_map(DEMO_MAP, fleet, truth, {r: np.array(p) for r, p in POSITIONS.items()})
    empty, _ = score_saved_map(empty_map, fleet, truth, {r: np.array(p) for r, p in POSITIONS.items()})
    assert demo.observable_from == empty.observable_from == "sensor poses"
    assert demo.observable_voxels == empty.observable_voxels > 1000
    assert empty.coverage == 0.0 and demo.coverage > 0.8
    by_map, _ = score_saved_map(empty_map, fleet, truth)
    assert by_map.observable_from == "scored map's free space" and by_map.observable_voxels == 0
