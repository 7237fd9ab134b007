"""Fleet files written for benchmarks elsewhere still find their site and routes."""

import os

from cps_fleet.fleet import load_fleet
from cps_harness.fleets import fleet_doc_with_absolute_paths, write_fleet_with_copies


def test_copied_fleet_loads_from_another_folder(tmp_path):
    doc = fleet_doc_with_absolute_paths()
    assert os.path.isabs(doc["site"]) and all(os.path.isabs(r["route"]) for r in doc["robots"])
    fleet = load_fleet(write_fleet_with_copies(str(tmp_path), copies=1))
    originals = load_fleet().robot_names
    assert fleet.robot_names == originals + [f"{name}2" for name in originals]
