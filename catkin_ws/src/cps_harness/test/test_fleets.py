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


def test_repeated_routes_are_routes_the_robots_accept(tmp_path):
    """Each lap goes there and back and home again (a flyer at its flight height), as the fleet's
    controller validates every waypoint."""
    from cps_fleet.fleet import check_fleet_routes, load_route
    from cps_fleet.site import load_site
    from cps_harness.fleets import write_fleet_with_repeated_routes
    from cps_sim.controllers import validate_route

    fleet = load_fleet(write_fleet_with_repeated_routes(str(tmp_path), laps=3))
    check_fleet_routes(fleet)
    site = load_site(fleet.site_path)
    for robot, original in zip(fleet.robots, load_fleet().robots):
        route, one_way = load_route(robot.route_path), load_route(original.route_path)
        validate_route(route, site, robot.robot_type)
        assert len(route.waypoints) == 3 * 2 * len(one_way.waypoints)
