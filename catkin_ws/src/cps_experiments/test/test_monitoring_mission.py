"""The monitoring phase for real: a short characterization mission of two robots along the storage
area, then the same routes on a site where one crate is gone and one moved 1 m
(cps_bringup/config/site_changes.yaml). Both changes are detected at the twin, live and in the
saved maps, within 0.2 m, with no other change (no robot, no place seen from another angle: issue
25); and the bad inputs of a monitoring mission are refused before anything starts."""

import os
import subprocess
import sys

import pytest
import yaml

from cps_ros.processes import processes_named

HERE = os.path.dirname(os.path.abspath(__file__))
CLI = os.path.join(HERE, "..", "..", "cps_bringup", "nodes", "cps_bringup")
CONFIG = os.path.join(HERE, "..", "..", "cps_bringup", "config")
CHANGES = os.path.join(CONFIG, "site_changes.yaml")
MAX_POSITION_ERROR_M = 0.2

# scout's lidar along the aisle west of the storage area; iris (camera pitched down) flies south
# over its west half at 3 m, so both crates are seen from above and the side.
ROUTES = {
    "scout": ({"x": 1.0, "y": 0.5, "z": 0.0, "yaw_deg": -90.0}, [{"x": 1.0, "y": -5.5}]),
    "iris": (
        {"x": 0.0, "y": 1.0, "z": 0.0, "yaw_deg": -90.0},
        [{"x": 3.2, "y": 1.0, "z": 3.0}, {"x": 3.2, "y": -5.0, "z": 3.0, "inspect": True}],
    ),
}


def _short_fleet(tmp_path):
    doc = yaml.safe_load(open(os.path.join(CONFIG, "fleet.yaml")))
    doc["site"] = os.path.normpath(os.path.join(CONFIG, doc["site"]))
    robots = []
    for robot in doc["robots"]:
        if robot["name"] in ROUTES:
            pose, waypoints = ROUTES[robot["name"]]
            route = tmp_path / f"{robot['name']}_route.yaml"
            route.write_text(yaml.safe_dump({"waypoints": waypoints}))
            robots.append({**robot, "initial_pose": pose, "route": str(route)})
    doc["robots"] = robots
    path = tmp_path / "fleet.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return str(path)


def _bringup(*args, timeout_s=400):
    result = subprocess.run([sys.executable, CLI, "all", *args], capture_output=True, text=True, timeout=timeout_s)
    return result.returncode, result.stdout + result.stderr


@pytest.mark.ros
@pytest.mark.slow
def test_removed_and_moved_crates_are_found(open_tmp_path):
    tmp_path = open_tmp_path  # the nodes run unprivileged: pytest's tmp_path is root-only
    from cps_experiments.monitor_report import evaluate_monitoring

    from cps_fleet.fleet import load_fleet

    fleet_file = _short_fleet(tmp_path)
    base, monitor = tmp_path / "baseline", tmp_path / "monitor"
    code, log = _bringup("--fleet", fleet_file, "--out", str(base), "--duration", "120")
    assert code == 0 and "every robot finished its route" in log, log[-3000:]
    code, log = _bringup(
        "--fleet",
        fleet_file,
        "--out",
        str(monitor),
        "--duration",
        "120",
        "--baseline",
        str(base / "map.bt"),
        "--site-changes",
        CHANGES,
    )
    assert code == 0 and "every robot finished its route" in log, log[-3000:]
    assert not processes_named(str(tmp_path)), processes_named(str(tmp_path))

    result = evaluate_monitoring(str(base / "map.bt"), str(monitor / "map.bt"), load_fleet(fleet_file), CHANGES)
    found = {
        (result.expected[m.expected_index].name, result.expected[m.expected_index].kind): m.position_error_m
        for m in result.score.matches
    }
    summary = [(c.kind, c.centroid_m, c.size_m, c.voxels) for c in result.detected]
    assert set(found) == {("crate_2", "disappeared"), ("crate_4", "disappeared"), ("crate_4", "appeared")}, summary
    assert max(found.values()) <= MAX_POSITION_ERROR_M, (found, summary)

    # Live at the twin: the map server's last detection saw them too, and asked for a closer look.
    live = (monitor / "map_changes.md").read_text()
    assert "disappeared" in live and "appeared" in live, live
    server_log = "".join(p.read_text() for p in (monitor / "logs").glob("map_server-*.log"))
    assert "high priority granted" in server_log, server_log[-3000:]

    # Every reported change is a real one (issue 25): the robots' bodies are not compared (their
    # poses were saved with both maps) and a change needs evidence, not a difference.
    assert result.baseline_trails is not None and result.current_trails is not None
    assert result.score.precision == 1.0, (result.score.precision, result.evidence, summary)


def test_monitoring_inputs_are_checked_before_anything_starts(tmp_path):
    import numpy as np

    from cps_fleet.fleet import load_fleet
    from cps_mapping.fused_map import FusedLogOddsMap

    corrupt = tmp_path / "corrupt.bt"
    corrupt.write_bytes(b"not an octomap")
    mapping = load_fleet().mapping
    good, coarse = str(tmp_path / "good.bt"), str(tmp_path / "coarse.bt")
    for path, resolution_m in ((good, mapping.resolution_m), (coarse, 2 * mapping.resolution_m)):
        fused = FusedLogOddsMap(resolution_m, mapping.sensor_model)
        fused.insert_batch([(np.array([[1.0, 1.0, 0.5]]), np.zeros(3))], 10.0, "r")
        fused.save(path)
    bad_changes = tmp_path / "changes.yaml"
    bad_changes.write_text("removed: [crate_2]\nmoved:\n  - {name: crate_4, dx_m: 30.0}\n")
    cases = [
        (("--site-changes", CHANGES), "needs --baseline"),
        (("--baseline", str(tmp_path / "none.bt")), "does not exist"),
        (("--baseline", str(corrupt)), "baseline map refused"),
        (("--baseline", coarse), "differs from the map's"),
        (("--baseline", good, "--site-changes", str(bad_changes)), f"{bad_changes}:3: moved[0]: moved equipment"),
    ]
    for args, words in cases:
        code, log = _bringup("--out", str(tmp_path / "out"), *args, timeout_s=60)
        assert code == 2 and words in log, (args, log[-2000:])
