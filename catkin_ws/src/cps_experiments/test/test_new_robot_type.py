"""A robot type defined only in a test's fleet file (other cloud topic, sensor frame, range and
limits) is simulated, carried through the tissue and mapped: a real robot is data, not code."""

import os
import subprocess
import sys

import pytest

BRINGUP = os.path.join(os.path.dirname(__file__), "..", "..", "cps_bringup", "nodes", "cps_bringup")
FLEET_TESTS = os.path.join(os.path.dirname(__file__), "..", "..", "cps_fleet", "test")


@pytest.mark.ros
@pytest.mark.slow
def test_new_type_is_simulated_and_mapped(open_tmp_path):
    tmp_path = open_tmp_path  # the nodes run unprivileged: pytest's tmp_path is root-only
    sys.path.insert(0, FLEET_TESTS)
    try:
        from test_robot_types import fleet_with_new_type
    finally:
        sys.path.remove(FLEET_TESTS)
    from cps_experiments.report import score_saved_map

    from cps_fleet.fleet import load_fleet

    fleet_path = fleet_with_new_type(tmp_path)
    out = tmp_path / "out"
    result = subprocess.run(
        [
            sys.executable,
            BRINGUP,
            "all",
            "--fleet",
            str(fleet_path),
            "--robots",
            "scout",
            "--duration",
            "15",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    log = result.stdout + result.stderr
    assert result.returncode == 0, log[-4000:]
    sim_log = "\n".join(p.read_text() for p in (out / "logs").rglob("fleet_sim-*.log"))
    assert "scout" in sim_log

    fleet = load_fleet(str(fleet_path)).with_robots(["scout"])
    score, _ = score_saved_map(str(out / "map.bt"), fleet, str(tmp_path / "ground_truth.npz"))
    print(
        f"tracked_lidar scout alone, 15 s: {score.map_voxels} voxels, within ±1 voxel: precision "
        f"{score.tolerant.precision:.3f}, F1 {score.tolerant.f1:.3f} (voxel for voxel {score.exact.f1:.3f})"
    )
    assert score.map_voxels > 5000 and score.tolerant.precision > 0.9, score.as_dict()
