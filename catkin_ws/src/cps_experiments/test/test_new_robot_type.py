"""A robot type defined only in a test's fleet file (other cloud topic, sensor frame, range and
limits) is simulated, carried through the tissue and mapped: a real robot is data, not code. In the
reference mission, scout is of such a type (cps_harness.fleets.NEW_TYPE)."""

import json

from cps_fleet.fleet import load_fleet
from cps_harness.fleets import NEW_TYPE_NAME

ROBOT = "scout"


def _report_row(report, robot):
    """The robot's row of the report's map server table, {column: text}."""
    lines = report.splitlines()
    header = next(i for i, line in enumerate(lines) if line.startswith("| robot | final state | clouds inserted"))
    columns = [c.strip() for c in lines[header].strip("|").split("|")]
    for line in lines[header + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] == robot:
            return dict(zip(columns, cells))
    raise AssertionError(f"no row for {robot} in the report's map server table")


def test_new_type_is_simulated_and_mapped(reference_mission):
    reference_mission.check()
    fleet = load_fleet(reference_mission.fleet_file)
    assert fleet.robot(ROBOT).type == NEW_TYPE_NAME
    out = reference_mission.out
    sim_log = "\n".join(p.read_text() for p in (out / "logs").rglob("fleet_sim-*.log"))
    assert ROBOT in sim_log

    row = _report_row((out / "report.md").read_text(), ROBOT)
    scores = json.loads((out / "scores.json").read_text())
    print(f"{NEW_TYPE_NAME} {ROBOT} in the reference mission: {row}; map precision within ±1 voxel {scores}")
    assert int(row["clouds inserted"]) > 0, row
    assert int(row["occupied voxels last updated"]) > 5000, row
    assert scores["precision_within_1_voxel"] > 0.9, scores
